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
