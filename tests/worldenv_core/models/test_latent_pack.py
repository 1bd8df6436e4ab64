"""Latent packs: a world model's open-loop training set as its autoencoder's latents."""
import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import WEIGHTS, CheckpointError
from worldenv_core.models.latent_pack import PackedMeta, read_latent_pack, write_latent_pack

TASK = {"task": "tiny", "suite": "libero_goal", "image_size": 8, "chunk": 4, "action_dim": 7, "proprio_dim": 7}


class Episode:
    def __init__(self, length, task_id, seed, source="expert"):
        rng = np.random.default_rng(seed)
        self.proprio, self.actions = rng.normal(size=(length + 1, 7)), rng.normal(size=(length, 7))
        self.joint_pos = rng.normal(size=(length + 1, 7))
        self.meta, self.length = PackedMeta(task_id, source), length


def model_dir(tmp_path, name, shift=0.0):
    folder = tmp_path / name
    folder.mkdir()
    save_file({"autoencoder.w": torch.ones(4) + shift, "latent_scale": torch.tensor(2.0),
               "velocity.w": torch.randn(4)}, str(folder / WEIGHTS))
    return folder


def test_a_pack_reads_back_for_its_autoencoder_only_and_thins_by_episode(tmp_path):
    model = model_dir(tmp_path, "m")
    episodes = [Episode(5, 0, 0), Episode(3, 1, 1, "policy"), Episode(4, 0, 2)]
    latents = [torch.randn(ep.length + 1, 2, 2, 2) for ep in episodes]
    arms = {0: {"eef": 12}, 1: {"eef": 12}}  # each scene's arm, for a model that draws it
    path = write_latent_pack(tmp_path / "p.st", latents, episodes, ["a", "b", "c"], model, "agentview", TASK, arms)
    pack = read_latent_pack(path, model)
    assert pack.keys == ["a", "b", "c"] and pack.task == TASK and pack.arms == arms and pack.every(2).arms == arms
    assert np.array_equal(pack.episodes[1].joint_pos, episodes[1].joint_pos)
    assert torch.equal(pack.chunks(type("M", (), {"memory_offsets": (0,), "chunk": 2})(), 1)[0]["joints"],
                       torch.from_numpy(episodes[0].joint_pos[1:3]))
    assert [ep.meta.task_id for ep in pack.episodes] == [0, 1, 0] and pack.episodes[1].length == 3
    assert [ep.meta.source for ep in pack.episodes] == ["expert", "policy", "expert"]  # what demo_share weighs
    assert all(torch.allclose(a, b, atol=1e-2) for a, b in zip(pack.latents, latents))  # stored as fp16
    assert np.allclose(pack.episodes[2].actions, episodes[2].actions, atol=1e-6)
    assert pack.every(2).keys == ["a", "c"] and len(pack.every(2).latents) == 2
    # the flow network may change (phase 3 trains it); another autoencoder may not
    save_file({"autoencoder.w": torch.ones(4), "latent_scale": torch.tensor(2.0), "velocity.w": torch.zeros(4)},
              str(model / WEIGHTS))
    assert read_latent_pack(path, model).keys == ["a", "b", "c"]
    with pytest.raises(CheckpointError, match="another autoencoder"):
        read_latent_pack(path, model_dir(tmp_path, "other", shift=1e-3))


def test_a_wrong_pack_is_one_line_naming_it(tmp_path):
    model = model_dir(tmp_path, "m")
    with pytest.raises(ConfigError, match="no latent pack at .*latents_to="):
        read_latent_pack(tmp_path / "missing.st", model)
    with pytest.raises(CheckpointError, match="is not a latent pack"):
        read_latent_pack(model / WEIGHTS, model)
    with pytest.raises(ValueError, match="2 latents for 6 frames"):
        write_latent_pack(tmp_path / "p.st", [torch.zeros(2, 1, 1, 1)], [Episode(5, 0, 0)], ["a"], model, "agentview",
                          TASK)
