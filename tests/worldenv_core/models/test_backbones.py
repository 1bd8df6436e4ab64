"""The world-model-latent frame encoder: it sees through a trained world simulator's autoencoder
(copied in from the checkpoint, frozen), its weights travel in the reflector's checkpoint, and a
world model with another autoencoder is refused by name."""
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.models.backbones import WorldModelLatentBackbone
from worldenv_core.models.checkpoint import CheckpointError, load_model, save_model

WORLD = {"_target_": "worldenv_core.models.worldsim.WorldSimulator", "image_size": 32, "chunk": 4,
         "memory_offsets": [0, 2], "latent_size": 8, "latent_channels": 4, "ae_widths": [8, 16], "width": 16,
         "map_channels": 4, "sampling_steps": 1}
LATENT = {"_target_": "worldenv_core.models.backbones.WorldModelLatentBackbone", "cameras": ["agentview"],
          "cond_dim": 6, "image_size": 32, "latent_size": 8, "latent_channels": 4, "ae_widths": [8, 16],
          "ae_patch": 4, "widths": [8, 16], "keypoints": 4}


@pytest.fixture
def world(tmp_path):
    torch.manual_seed(0)
    model = instantiate(WORLD)
    model.latent_scale.fill_(2.5)
    return model, save_model(tmp_path / "world", model, WORLD, {"kind": "worldsim"})


def test_the_latent_encoder_copies_the_world_models_autoencoder_and_keeps_it_frozen(world, tmp_path):
    model, path = world
    enc = instantiate(LATENT).requires_grad_(True)
    enc.load_autoencoder(str(path))
    for k, v in model.autoencoder.state_dict().items():
        assert torch.equal(enc.autoencoder.state_dict()[k], v)
    assert float(enc.latent_scale) == 2.5 and not any(p.requires_grad for p in enc.autoencoder.parameters())
    assert any(p.requires_grad for p in enc.blocks.parameters())
    images = {"agentview": torch.rand(3, 3, 32, 32)}
    out = enc.train()(images, torch.zeros(3, 6))
    assert out.shape == (3, enc.out_dim) and not enc.autoencoder.training
    # the reflector checkpoint carries the autoencoder: rebuilt from its config alone, it scores the same
    save_model(tmp_path / "enc", enc, LATENT, {"kind": "reflector"})
    again, _ = load_model(tmp_path / "enc")
    assert torch.allclose(again.eval()(images, torch.zeros(3, 6)), enc.eval()(images, torch.zeros(3, 6)))


def test_a_world_model_with_another_autoencoder_is_refused(world):
    _, path = world
    enc = WorldModelLatentBackbone(["agentview"], 6, image_size=32, latent_size=8, latent_channels=3, ae_widths=(8, 16),
                                   widths=(8, 16))
    with pytest.raises(CheckpointError, match="another autoencoder"):
        enc.load_autoencoder(str(path))
