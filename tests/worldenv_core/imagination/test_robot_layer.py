"""The robot layer: the real renderer's robot at tracked joints, pasted over imagined frames and fed back."""
import numpy as np
import pytest
import torch

from tests.conftest import TINY_SUITE, TINY_TASK
from worldenv_core.imagination.robot_layer import RobotLayer, Scene, composite


def test_composite_takes_the_robots_pixels_and_keeps_the_rest():
    frames = torch.zeros(2, 3, 4, 4, dtype=torch.uint8)
    rgb = np.full((2, 4, 4, 3), 200, np.uint8)
    mask = np.zeros((2, 4, 4), bool)
    mask[0, 1, 2] = mask[1, 3, 0] = True
    out = composite(frames, rgb, mask)
    assert out.dtype == torch.uint8 and out.shape == frames.shape
    assert out[0, :, 1, 2].tolist() == [200] * 3 and out[1, :, 3, 0].tolist() == [200] * 3
    assert int(out.sum()) == 2 * 3 * 200  # nothing else changed


@pytest.mark.sim
def test_the_robot_is_drawn_where_the_real_simulator_puts_it(tiny_env):
    """The arm moved and the gripper closed for real: tracked from the end-effector states alone, the layer's
    robot covers the real render's robot pixels, in the same colours."""
    frame = tiny_env.reset(seed=3)
    scene = Scene(TINY_TASK, 3, frame.sim_state.copy())
    states = []
    for t in range(16):
        move = [0.6, 0.0, -0.3, 0, 0, 0, 1.0 if t >= 8 else -1.0]  # forward and down, then close the fingers
        states.append(tiny_env.step(np.array(move)).proprio)
    real = tiny_env.render(["agentview"])["agentview"]
    layer = RobotLayer(TINY_SUITE, "agentview", 64)
    try:
        layer.reset([scene], torch.as_tensor(frame.joint_pos)[None])
        rgb, mask = layer.advance(torch.as_tensor(np.stack(states))[None])
        assert rgb.shape == (1, 64, 64, 3) and mask.shape == (1, 64, 64) and mask.sum() > 100
        at_start = layer._draw(scene, frame.joint_pos, float(frame.proprio[6]))[1]
        assert (mask[0] != at_start).sum() > 20, "the robot did not move with the tracked joints"
        # inside the layer's robot the real frame shows the robot too: the same pixels, up to edges
        diff = np.abs(rgb[0].astype(int) - real.astype(int)).mean(-1)[mask[0]]
        assert np.median(diff) < 8, f"the drawn robot is not where the real one is (median |diff| {np.median(diff)})"
    finally:
        layer.close()


@pytest.mark.sim
def test_an_imagined_step_shows_the_layers_robot_and_continues_from_it(make_env, tiny_env):
    frame = tiny_env.reset(seed=5)
    env = make_env(eta=1.0, horizon=8)  # R > 1 never: no verdict fires
    env.robot = RobotLayer(TINY_SUITE, "agentview", 32)
    from worldenv_core.imagination.env import Context

    image = torch.from_numpy(tiny_env.render(["agentview"])["agentview"][::2, ::2].copy()).permute(2, 0, 1)
    ctx = Context(task_id=TINY_TASK, instruction="t", frame=image.contiguous(),
                  proprio=torch.as_tensor(frame.proprio), joint_pos=torch.as_tensor(frame.joint_pos),
                  scene=Scene(TINY_TASK, 5, frame.sim_state.copy()))
    try:
        env.reset([ctx, ctx])
        state = env.step(torch.zeros(2, env.chunk, 7))
        rgb, mask = env.robot._draw(ctx.scene, env.robot.joints[0].numpy(), float(state.proprio[0, 6]))
        assert mask.sum() > 10 and torch.equal(state.frames[0].permute(1, 2, 0)[torch.from_numpy(mask)],
                                               torch.from_numpy(rgb[mask]))
        # the next chunk starts from the composited frame: its latent is the encoded composite
        assert torch.allclose(env.sim.latents[:, -1], env.sim.model.encode(state.frames[:, None])[:, 0])
        with pytest.raises(ValueError, match="needs its scene and joint angles"):
            env.reset([Context(task_id=TINY_TASK, instruction="t", frame=image.contiguous(),
                               proprio=torch.as_tensor(frame.proprio))])
    finally:
        env.robot.close()
