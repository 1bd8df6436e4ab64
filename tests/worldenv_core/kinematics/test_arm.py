"""The arm's skeleton: its chain against the simulator's, its joints tracked from end-effector
states, and the links the action map draws against where the camera sees the robot."""
import numpy as np
import pytest
import torch

from worldenv_core.kinematics import PinholeCamera, draw_action_maps
from worldenv_core.kinematics.action_map import ARM_SHADE, arm_mask
from worldenv_core.kinematics.arm import PATH, SEGMENT_RADIUS_M, SerialArm, track


@pytest.fixture(scope="module")
def arm_and_traj(tiny_env):
    from worldenv_core.envs.recording import expert_attempt

    arm = SerialArm.from_env(tiny_env, tiny_env.reset(init_state=0))
    traj = expert_attempt(tiny_env, 0, seed=0, max_steps=tiny_env.max_steps)
    assert traj.error is None and traj.length > 50
    return arm, traj


@pytest.mark.sim
def test_the_serial_chain_is_the_simulators(tiny_env, arm_and_traj):
    from worldenv_core.kinematics.chain import PandaChain

    arm, traj = arm_and_traj
    chain = PandaChain.from_env(tiny_env)
    q = torch.rand(8, 7, dtype=torch.float64) * 2 - 1
    full = chain.chain.forward_kinematics(torch.nn.functional.pad(q, (0, 2)))
    mine = arm.transforms(q)
    for i, name in enumerate(PATH):
        np.testing.assert_allclose(mine[:, i].numpy(), full[name].get_matrix().numpy(), atol=1e-9)
    back = SerialArm.from_dict(arm.to_dict())  # what a world model's metadata carries
    np.testing.assert_allclose(back.points(q).numpy(), arm.points(q).numpy())
    # the recorded proprio orientation is the grip site's, turned by the stored constant
    from worldenv_core.kinematics.next_state import axis_angle_to_matrix

    joints = torch.tensor(np.stack([f.joint_pos for f in traj.frames]))
    proprio = torch.tensor(np.stack([f.proprio for f in traj.frames]), dtype=torch.float64)
    pos, rot = arm.eef_pose(joints)
    assert (pos - proprio[:, :3]).norm(dim=-1).max() < 3e-3  # observations lag a physics substep
    site = arm.site_rotation(axis_angle_to_matrix(proprio[:, 3:6]))
    assert (site.transpose(-1, -2) @ rot - torch.eye(3, dtype=torch.float64)).abs().max() < 0.02


@pytest.mark.sim
def test_tracked_joints_follow_the_recorded_arm(arm_and_traj):
    """From the first frame's joints and then only the end-effector states, the skeleton stays on
    the recorded one for the whole episode: minimal joint motion is what the controller does."""
    arm, traj = arm_and_traj
    joints = torch.tensor(np.stack([f.joint_pos for f in traj.frames]))
    proprio = torch.tensor(np.stack([f.proprio for f in traj.frames]), dtype=torch.float64)
    tracked = track(arm, joints[:1], proprio[None, 1:])[0]
    err_mm = (arm.points(tracked) - arm.points(joints[1:])).norm(dim=-1) * 1000
    assert err_mm.median() < 2.0 and err_mm.quantile(0.9) < 20.0 and err_mm.max() < 40.0
    # standing still: the arm does not move
    still = track(arm, joints[:1], proprio[None, :1].expand(1, 5, 7))[0]
    assert (arm.points(still) - arm.points(joints[:1])).norm(dim=-1).max() < 2e-3


@pytest.mark.sim
def test_the_drawn_arm_is_where_the_camera_sees_the_robot(tiny_env, arm_and_traj):
    arm, traj = arm_and_traj
    size = 128
    names = np.array([tiny_env.sim.model.geom_id2name(g) or "" for g in range(tiny_env.sim.model.ngeom)] + [""])
    robot_geom = np.char.startswith(names, "robot0_") | np.char.startswith(names, "gripper0_")
    scores = []
    for f in traj.frames[::30]:
        tiny_env.set_sim_state(f.sim_state)
        cam = PinholeCamera.from_sim(tiny_env.sim, "agentview", size)
        seg = tiny_env.sim.render(width=size, height=size, camera_name="agentview", segmentation=True)[::-1]
        robot = robot_geom[np.where(seg[..., 1] >= 0, seg[..., 1], -1)]
        points = arm.points(torch.tensor(f.joint_pos)[None]).float()
        plain = draw_action_maps(torch.tensor(f.proprio)[None], cam, size)[0]
        with_arm = draw_action_maps(torch.tensor(f.proprio)[None], cam, size, arm_points=points)[0]
        drawn = (with_arm.max(0).values > 0.1).numpy()
        both = (drawn & robot).sum()
        scores.append((both / robot.sum(), both / drawn.sum()))
        (mask,) = arm_mask(points, cam, size).numpy()  # the region open-loop fidelity scores the arm in
        assert (mask & robot).sum() / robot.sum() >= both / robot.sum() and mask.mean() < 0.5
        disc = (plain > 0.999).all(0)  # the gripper's disc stays white, over the links
        assert disc.any() and torch.equal(with_arm[:, disc], plain[:, disc])
        assert (with_arm.max(0).values > 0.1).sum() > 3 * (plain.max(0).values > 0.1).sum()
    recall, precision = np.mean(scores, axis=0)
    assert recall > 0.6 and precision > 0.6, f"the drawn arm covers {recall:.2f} of the robot at precision {precision:.2f}"


def _camera() -> PinholeCamera:
    """Looking down the world's -z from 2 m up: world x is the image's column, y its row (upward)."""
    return PinholeCamera(name="top", image_size=64, focal=64.0, position=np.array([0.0, 0.0, 2.0]), rotation=np.eye(3))


def test_the_nearest_link_is_drawn_in_front():
    n = len(SEGMENT_RADIUS_M) + 1
    far = torch.stack([torch.linspace(-0.4, 0.4, n), torch.zeros(n), torch.zeros(n)], dim=-1)  # along x, 2 m away
    near = torch.stack([torch.zeros(n), torch.linspace(-0.4, 0.4, n), torch.full((n,), 1.0)], dim=-1)  # along y, 1 m away
    state = torch.tensor([[5.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0]])  # the gripper far out of view
    maps = draw_action_maps(state.expand(2, 7), _camera(), arm_points=torch.stack([far, near]))
    assert maps.shape == (2, 3, 64, 64)
    both = draw_action_maps(state, _camera(), arm_points=far[None])  # one arm per state, batched or not
    assert torch.equal(both[0], maps[0])
    # the first link far along x, the third near along y: they cross at the image's centre
    crossing = torch.tensor([[-0.4, 0, 0], [0.4, 0, 0], [0, -0.4, 1]] + [[0, 0.4, 1]] * (n - 3))[None]
    centre = draw_action_maps(state, _camera(), arm_points=crossing)[0, :, 31:33, 31:33]
    shades = torch.linspace(*ARM_SHADE, n - 1)
    assert torch.allclose(centre, shades[2].expand_as(centre), atol=1e-4)  # the near link's grey, not the far one's
    assert maps[1].max(0).values.gt(0.1).sum() > maps[0].max(0).values.gt(0.1).sum()  # nearer links look thicker
    with pytest.raises(ValueError, match="skeleton has"):
        draw_action_maps(state, _camera(), arm_points=far[None, :3])
    with pytest.raises(ValueError, match="do not match"):
        draw_action_maps(state, _camera(), arm_points=far[None, None])
