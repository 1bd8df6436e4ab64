"""train_reflector with `reflector=worldsim_latent` on the tiny task: the reflector sees frames
through the world model's autoencoder, which it copies from the world model's checkpoint and
carries in its own."""
import pytest
import torch

from stages.train_reflector.run import run as train_reflector
from tests.stages.conftest import REFLECTOR, stage_cfg
from worldenv_core.manifest import Manifest
from worldenv_core.models.checkpoint import load_checkpoint

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def test_a_reflector_on_the_world_models_latent(tiny_models):
    exp = tiny_models
    metrics = train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR, "reflector=worldsim_latent",
                                        "reflector.frame_encoder.ae_widths=[8,16]"))
    assert "on the world model's latent" in metrics["training"]
    m = Manifest(exp)
    rec, world = m.latest("train_reflector", task="tiny"), m.latest("train_worldsim", task="tiny")
    assert world.id in rec.inputs  # the world model it sees through is an input of the run
    reflector, _ = load_checkpoint(m.resolve(rec, kind="checkpoint")[0].parent, "reflector")
    worldsim, _ = load_checkpoint(m.resolve(world, kind="checkpoint")[0].parent, "worldsim")
    for k, v in worldsim.autoencoder.state_dict().items():  # frozen through training, carried in the checkpoint
        assert torch.equal(reflector.frame_encoder.autoencoder.state_dict()[k], v)
    frames = torch.randint(0, 255, (3, 3, 64, 64), dtype=torch.uint8)
    scores = reflector.score_prefixes(frames, torch.zeros(384), [0, 2])
    assert scores.shape == (2,) and bool(((scores >= 0) & (scores <= 1)).all())
