"""The sampler override of the imagined simulator: the conditional mean is one answer whatever
the draw, a sampled simulator depends on it (the "sampled generation" lever of issue 22)."""
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
