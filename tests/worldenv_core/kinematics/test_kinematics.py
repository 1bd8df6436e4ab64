"""Kinematics against the real simulator: FK, camera projection, action maps, next-state model."""
import numpy as np
import pytest
import torch

from worldenv_core.envs.recording import expert_attempt
from worldenv_core.kinematics import NextStateModel, PinholeCamera, draw_action_maps
from worldenv_core.kinematics.chain import PandaChain
from worldenv_core.kinematics.next_state import axis_angle_to_matrix, state_errors

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def expert_traj(tiny_env):
    """A real expert episode (physics only): ~100 states spread over the workspace."""
    traj = expert_attempt(tiny_env, 0, seed=0, max_steps=tiny_env.max_steps)
    assert traj.error is None and traj.length > 50
    return traj


def _site_pose(env):
    sim = env.sim
    sid = sim.model.site_name2id("gripper0_grip_site")
    return np.array(sim.data.site_xpos[sid]), np.array(sim.data.site_xmat[sid]).reshape(3, 3)


def test_fk_matches_the_simulator_end_effector(tiny_env, expert_traj):
    chain = PandaChain.from_env(tiny_env)
    sim = tiny_env.sim
    joints = [sim.model.get_joint_qpos_addr(f"robot0_joint{i}") for i in range(1, 8)]
    frames = expert_traj.frames[::10]
    qpos = []
    for f in frames:
        tiny_env.set_sim_state(f.sim_state)
        qpos.append(np.array(sim.data.qpos[joints]))
    pos, rot = chain.fk(torch.tensor(np.stack(qpos)))
    for i, f in enumerate(frames):
        tiny_env.set_sim_state(f.sim_state)
        site_pos, site_rot = _site_pose(tiny_env)
        np.testing.assert_allclose(pos[i].numpy(), site_pos, atol=1e-6)
        np.testing.assert_allclose(rot[i].numpy(), site_rot, atol=2e-3)  # XML-rounded quats: < 0.1 deg
        # robosuite's observations lag the state they come with by about a physics substep (~1 mm)
        np.testing.assert_allclose(f.proprio[:3], site_pos, atol=3e-3)


def _gripper_pixels(env, size: int) -> np.ndarray:
    """(row, col) of the pixels where the camera sees a gripper geom, in the upright image."""
    seg = env.sim.render(width=size, height=size, camera_name="agentview", segmentation=True)[::-1]
    geom_ids = seg[..., 1]
    names = np.array([env.sim.model.geom_id2name(g) or "" if g >= 0 else "" for g in range(env.sim.model.ngeom)] + [""])
    mask = np.char.startswith(names[np.where(geom_ids >= 0, geom_ids, -1)], "gripper0_")
    return np.argwhere(mask)


def test_projected_end_effector_lands_on_the_gripper(tiny_env, expert_traj):
    size = 128
    for f in expert_traj.frames[::25]:
        tiny_env.set_sim_state(f.sim_state)
        cam = PinholeCamera.from_sim(tiny_env.sim, "agentview", size)
        (u, v), depth = (x.numpy() for x in cam.project(torch.tensor(f.proprio[:3], dtype=torch.float64)))
        assert depth > 0
        gripper = _gripper_pixels(tiny_env, size)
        assert len(gripper), "the gripper is not visible from agentview"
        nearest = np.min(np.hypot(gripper[:, 0] - v, gripper[:, 1] - u))
        # the grip site sits between the fingertips: within 5 px (4 % of the width) of a finger
        assert nearest <= 5.0, f"projected eef ({u:.1f}, {v:.1f}) is {nearest:.1f} px from the gripper"


def test_action_map_marker_sits_at_the_projection(tiny_env, expert_traj):
    tiny_env.set_sim_state(expert_traj.frames[0].sim_state)
    cam = PinholeCamera.from_sim(tiny_env.sim, "agentview", 64)
    states = torch.tensor(np.stack([f.proprio for f in expert_traj.frames[:16]]))
    states[1, 6], states[2, 6] = 1.0, 0.0  # one open, one closed gripper
    maps = draw_action_maps(states.reshape(2, 8, 7), cam)
    assert maps.shape == (2, 8, 3, 64, 64) and maps.min() >= 0 and maps.max() <= 1
    flat = maps.reshape(16, 3, 64, 64)
    uv, _ = cam.project(states[:, :3])
    for i in range(16):
        r, c = int(round(float(uv[i, 1]))), int(round(float(uv[i, 0])))
        assert flat[i, :, r, c].max() > 0.5  # the marker is drawn where the eef projects
        ys, xs = torch.nonzero(flat[i].max(0).values > 0.5, as_tuple=True)
        assert (ys - r).abs().max() < 12 and (xs - c).abs().max() < 12  # and nowhere else
    area = (flat.max(1).values > 0.5).flatten(1).sum(1)
    assert area[1] > area[2]  # an open gripper draws a larger disc than a closed one


def test_the_gripper_mask_covers_the_real_gripper_and_little_else(tiny_env, expert_traj):
    """The region open-loop fidelity scores the robot in: around the projected grip site, holding the
    gripper's rendered pixels, a small share of the frame."""
    from worldenv_core.kinematics.action_map import gripper_mask

    size = 128
    for f in expert_traj.frames[::50]:
        tiny_env.set_sim_state(f.sim_state)
        cam = PinholeCamera.from_sim(tiny_env.sim, "agentview", size)
        (mask,) = gripper_mask(torch.tensor(f.proprio[None]), cam, size)
        gripper = _gripper_pixels(tiny_env, size)
        inside = mask[torch.as_tensor(gripper[:, 0]), torch.as_tensor(gripper[:, 1])].float().mean()
        assert inside > 0.8, f"{inside:.2f} of the gripper's pixels in its mask"
        assert 0.0 < mask.float().mean() < 0.08  # pi x 0.15^2 of the frame when all of it is inside


def test_axis_angle_round_trip():
    v = torch.tensor([[0.3, -1.2, 2.0], [0.0, 0.0, 1e-3]], dtype=torch.float64)
    from pytorch_kinematics.transforms import matrix_to_axis_angle

    np.testing.assert_allclose(matrix_to_axis_angle(axis_angle_to_matrix(v)).numpy(), v.numpy(), atol=1e-9)


def test_next_state_model_tracks_the_simulator(expert_traj):
    class Ep:
        proprio = np.stack([f.proprio for f in expert_traj.frames]).astype(np.float64)
        actions = np.stack(expert_traj.actions).astype(np.float64)

    aim = NextStateModel()  # where the controller aims
    fitted = NextStateModel.fit([Ep])
    assert 0 < fitted.g_pos < 1.5 and 0 < fitted.g_rot < 1.5 and 0 < fitted.grip_lag < 1
    assert fitted.grip_closed < fitted.grip_open
    for h in (1, 8):
        e_aim, e_fit = state_errors(aim, [Ep], h), state_errors(fitted, [Ep], h)
        assert e_fit["pos_mm_median"] < e_aim["pos_mm_median"]
    one = state_errors(fitted, [Ep], 1)
    assert one["pos_mm_median"] < 3.0 and one["rot_deg_median"] < 2.0
    # the lagging gripper against the first model's constant rate fitted on the same episode
    constant = NextStateModel(**{k: v for k, v in fitted.to_dict().items() if not k.startswith("grip_") and k != "g_grip"},
                              g_grip=_constant_rate(Ep))
    for h in (8, 32):
        assert state_errors(fitted, [Ep], h)["grip_mae"] < state_errors(constant, [Ep], h)["grip_mae"]


def _constant_rate(ep) -> float:
    """The first model's gripper rate: the median opening change per unit command over moving steps."""
    d, a = np.diff(ep.proprio[:, 6]), -np.clip(ep.actions[:, 6], -1, 1)
    moving = np.abs(d) > 1e-3
    return float(np.median(d[moving] / a[moving]))


def test_gripper_lags_toward_its_levels_and_the_first_model_still_loads():
    lag = NextStateModel(grip_lag=0.2, grip_momentum=0.3, grip_closed=0.01, grip_open=0.99)  # settles without overshoot
    state = torch.tensor([[0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 0.99]], dtype=torch.float64)
    close = torch.zeros(1, 30, 7, dtype=torch.float64)
    close[..., 6] = 1.0
    states, carry = lag.rollout(state, close)
    grip = states[0, :, 6].numpy()
    assert np.all(np.diff(grip) <= 1e-12) and grip[0] > 0.7 and abs(grip[-1] - 0.01) < 0.02 and grip.min() >= 0.01
    assert len(carry) == 3
    # open, close, open again: the fit finds the levels it settles at and the lag between them
    actions = torch.zeros(1, 150, 7, dtype=torch.float64)
    actions[0, :, 6] = torch.tensor([-1.0] * 50 + [1.0] * 50 + [-1.0] * 50)
    start = state.clone()
    start[0, 6] = 0.5
    ep = type("Ep", (), {"proprio": torch.cat([start, lag.rollout(start, actions)[0][0]]).numpy(),
                         "actions": actions[0].numpy()})
    fitted = NextStateModel.fit([ep])
    assert abs(fitted.grip_lag - 0.2) < 0.01 and abs(fitted.grip_momentum - 0.3) < 0.01
    assert abs(fitted.grip_closed - 0.01) < 1e-3 and abs(fitted.grip_open - 0.99) < 1e-3
    first = NextStateModel(g_grip=0.1)  # saved before grip_lag: a constant rate, clipped to [0, 1]
    np.testing.assert_allclose(first.rollout(state, close)[0][0, :3, 6].numpy(), [0.89, 0.79, 0.69])
