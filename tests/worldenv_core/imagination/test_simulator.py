"""The sampler override of the imagined simulator: the conditional mean is one answer whatever
the draw, a sampled simulator depends on it (the "sampled generation" lever of verdict fidelity)."""
import pytest
import torch

from tests.worldenv_core.imagination.conftest import TINY, camera
from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.kinematics import NextStateModel
from worldenv_core.models.worldsim import WorldSimulator


def _chunk(noise, seed):
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**{**TINY, "noise_scale": 1.0}), NextStateModel(), camera(2.0),
                            sampling_steps=2, noise_scale=noise)
    sim.reset(torch.full((2, 1, 3, 32, 32), 128, dtype=torch.uint8), torch.tensor([[0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0]] * 2))
    return sim.step(torch.zeros(2, TINY["chunk"], 7), decode="none", generator=torch.Generator().manual_seed(seed)).latents


def test_the_sampler_noise_override_chooses_mean_or_sample():
    assert torch.equal(_chunk(0.0, 1), _chunk(0.0, 2))  # the conditional mean: the draw does not matter
    assert not torch.allclose(_chunk(1.0, 1), _chunk(1.0, 2))  # sampled: it does
    assert torch.equal(_chunk(None, 1), _chunk(1.0, 1))  # None: the model's own temperature (here 1)
    with pytest.raises(ValueError, match="noise_scale"):
        _chunk(1.5, 1)


def test_replay_from_steps_imagines_each_start_open_loop_and_needs_the_state_before_it():
    from worldenv_core.imagination.simulator import replay_from_steps

    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    imgs = torch.randint(0, 255, (11, 3, 32, 32), dtype=torch.uint8)
    proprio, actions = torch.zeros(11, 7), torch.zeros(10, 7)
    frames = replay_from_steps(sim, imgs, proprio, actions, [1, 9], n_chunks=3)  # past the end: the last action held
    assert frames.shape == (2, 3 * TINY["chunk"], 3, 32, 32) and frames.dtype == torch.uint8
    with pytest.raises(ValueError, match="starts must be >= 1, got 0"):
        replay_from_steps(sim, imgs, proprio, actions, [0, 4], n_chunks=1)


def test_open_loop_fidelity_scores_each_horizon_against_copy_last():
    import numpy as np

    from tests.conftest import synthetic_episode
    from worldenv_core.imagination.simulator import open_loop_fidelity

    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    rng = np.random.default_rng(0)
    eps = [synthetic_episode(rng, size=32, length=30, succeed_at=12), synthetic_episode(rng, size=32, length=6)]
    out = open_loop_fidelity(sim, eps, horizons=(4, 8), starts_per_episode=2)
    assert out["horizons"][8]["n"] == 2  # two starts of the first episode; the second is too short for 8 steps
    real, imagined = out["videos"][0]
    assert real.shape == imagined.shape and imagined.shape[0] == 8
    assert all(0 < out["horizons"][h]["model_psnr"] < 100 for h in (4, 8))
    for h in (4, 8):  # the gripper's region scored apart (the synthetic episodes' proprio projects into the frame)
        row = out["horizons"][h]
        assert 0 < row["model_psnr_gripper"] < 100 and -1 <= row["model_ssim_gripper"] <= 1
        assert -1 <= row["copy_ssim_gripper"] <= 1


def test_rendered_copy_draws_every_frame_but_the_context_through_the_world_model():
    from worldenv_core.imagination.simulator import rendered_copy

    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    imgs = torch.randint(0, 255, (9, 3, 32, 32), dtype=torch.uint8)
    out = rendered_copy(sim, imgs, block=4)  # blocks of 4: the last one short
    assert out.shape == imgs.shape and out.dtype == torch.uint8
    assert torch.equal(out[0], imgs[0]) and not torch.equal(out[1:], imgs[1:])
    assert torch.equal(out, rendered_copy(sim, imgs, block=64))  # frame by frame: blocks do not matter


def _toy_arm():
    """A 7-joint arm under the test camera: links of 8 cm along x, joints turning about z, y and x."""
    import numpy as np

    from worldenv_core.kinematics.arm import SerialArm

    def shift(x, z=0.0):
        m = np.eye(4)
        m[0, 3], m[2, 3] = x, z
        return m

    offsets = [shift(-0.3, 0.5)] + [shift(0.08) for _ in range(7)] + [shift(0.05)]
    axes = [np.zeros(3)] + [np.eye(3)[2 - j % 3] for j in range(7)]
    axes.append(np.zeros(3))
    return SerialArm(np.stack(offsets), np.stack(axes), np.array([-1, 0, 1, 2, 3, 4, 5, 6, -1]), np.arange(8), 8, np.eye(3))


def test_a_world_model_drawing_the_arm_tracks_its_joints_and_draws_its_links():
    from pytorch_kinematics.transforms import matrix_to_axis_angle

    from worldenv_core.kinematics.arm import skeletons

    arm = _toy_arm()
    q0 = torch.tensor([[0.5, 0.6, -0.4, 0.8, 0.3, -0.7, 0.4]] * 2, dtype=torch.float64)  # bent: away from singularities
    pos, rot = arm.eef_pose(q0)
    state = torch.cat([pos, matrix_to_axis_angle(rot), torch.ones(2, 1, dtype=torch.float64)], dim=-1)
    frames = torch.full((2, 1, 3, 32, 32), 128, dtype=torch.uint8)
    actions = torch.zeros(2, TINY["chunk"], 7)
    actions[:, :, 1] = 0.3  # along y

    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY, arm_map=True), NextStateModel(), camera(2.0), arm=arm)
    sim.reset(frames, state)  # without joints it can render, not step
    with pytest.raises(ValueError, match="joint angles"):
        sim.step(actions)
    sim.reset(frames, state, joints=q0)
    out = sim.step(actions, decode="none")
    assert out.joints.shape == (2, TINY["chunk"], 7)
    reached, _ = arm.eef_pose(out.joints.double())
    assert (reached - out.proprio[..., :3].double()).norm(dim=-1).max() < 5e-3  # within a third of a 15 mm step
    assert not torch.allclose(out.joints[:, -1].double(), q0)
    plain = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    plain.reset(frames, state)
    lit, gripper_only = out.action_maps.amax(2) > 0.1, plain.step(actions, decode="none").action_maps.amax(2) > 0.1
    assert (lit & ~gripper_only).flatten(2).sum(-1).min() >= 4  # every map draws links beyond the gripper's marks
    points = skeletons(out.joints.double(), [arm, arm])
    assert points.shape == (2, TINY["chunk"], 8, 3)


def test_an_imagined_env_drawing_the_arm_needs_each_contexts_joints(contexts):
    from hydra.utils import instantiate

    from tests.worldenv_core.imagination.conftest import REFLECTOR
    from worldenv_core.imagination.env import ImaginedEnv

    arm = _toy_arm()
    sim = ImaginedSimulator(WorldSimulator(**TINY, arm_map=True), NextStateModel(), camera(2.0), arm=arm)
    encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
    env = ImaginedEnv(sim, {0: camera(2.0), 3: camera(2.5)}, instantiate(REFLECTOR), encoder, 0.5, 8, {0: arm, 3: arm})
    ctx = contexts()
    with pytest.raises(ValueError, match="every context needs its joint angles"):
        env.reset(ctx)
    for c in ctx:
        c.joint_pos = torch.zeros(7, dtype=torch.float64)
    env.reset(ctx)
    step = env.step(torch.zeros(3, TINY["chunk"], 7))
    assert step.frames.shape == (3, 3, 32, 32) and sim.joints.shape == (3, 7)


def test_open_loop_fidelity_scores_the_arms_region_where_it_knows_the_arm_and_the_joints():
    import numpy as np

    from tests.conftest import synthetic_episode
    from worldenv_core.imagination.simulator import open_loop_fidelity

    torch.manual_seed(0)
    arm = _toy_arm()
    rng = np.random.default_rng(0)
    ep = synthetic_episode(rng, size=32, length=20)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0), arm=arm)
    assert np.isnan(open_loop_fidelity(sim, [ep], horizons=(4,), starts_per_episode=1)["horizons"][4]["model_ssim_arm"])
    ep.joint_pos = np.tile([0.5, 0.6, -0.4, 0.8, 0.3, -0.7, 0.4], (ep.num_frames, 1))  # a real episode's joints
    row = open_loop_fidelity(sim, [ep], horizons=(4,), starts_per_episode=1)["horizons"][4]
    assert -1 <= row["model_ssim_arm"] <= 1 and -1 <= row["copy_ssim_arm"] <= 1 and 0 < row["model_psnr_arm"] < 100


def test_a_chunk_not_decoded_whole_is_predicted_only_where_later_memories_read_it():
    """decode="last" predicts only the chunk positions later memories read (3 and 7 of 8 with the default
    memory): over several chunks, sampled with seeded generators, its frames and those positions' latents are
    the whole chunk's, at a quarter of the flow network's rows."""
    cfg = {**TINY, "chunk": 8, "memory_offsets": (0, 4, 8, 16), "noise_scale": 1.0, "sampling_steps": 2}
    torch.manual_seed(0)
    model = WorldSimulator(**cfg)
    torch.nn.init.normal_(model.velocity.out[-1].weight, std=0.1)  # a zero-initialised head would predict nothing
    assert model.read_rows == (3, 7) and WorldSimulator(**TINY).read_rows == (1, 3)
    calls = []
    model.velocity.register_forward_hook(lambda m, args, out: calls.append(out.shape[0]))
    actions = torch.randn(4, 2, 8, 7, generator=torch.Generator().manual_seed(1)) * 0.5
    out = {}
    for decode in ("all", "last"):
        sim = ImaginedSimulator(model, NextStateModel(), camera(2.0))
        frames = torch.randint(0, 255, (2, 3, 3, 32, 32), dtype=torch.uint8, generator=torch.Generator().manual_seed(2))
        sim.reset(frames, torch.tensor([[0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0]] * 2))
        gens = [torch.Generator().manual_seed(10 + i) for i in range(2)]
        out[decode] = [sim.step(a, decode=decode, generator=gens) for a in actions]
    for full, part in zip(out["all"], out["last"]):
        assert part.rows == (3, 7) and part.latents.shape[1] == 2
        assert torch.allclose(part.latents, full.latents[:, [3, 7]], atol=1e-5)
        assert (part.frames.int() - full.frames[:, -1:].int()).abs().max() <= 1  # the policy's frame
    assert calls[:8] == [2 * 8] * 8 and calls[8:] == [2 * 2] * 8  # 2 rollouts x rows, 2 Euler steps, 4 chunks
