import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from worldenv_core.data.dataset import EpisodeDataset
from worldenv_core.data.mcap_io import read_episode, write_episode

# episode_dir holds episodes of 10, 5 and 1 steps (seeds 0, 1, 2)


def test_frame_mode_items(episode_dir):
    ds = EpisodeDataset(episode_dir, cameras=["agentview", "wrist"], mode="frame")
    assert len(ds) == 10 + 5 + 1 and ds.num_episodes == 3
    ep1 = read_episode(ds.paths[1])
    item = ds[10 + 2]  # episode 1, frame 2
    assert item["episode_index"] == 1 and item["frame_index"] == 2
    img = item["images"]["wrist"]
    assert img.dtype == torch.uint8 and img.shape == (3, 32, 32)
    assert torch.equal(img, torch.from_numpy(ep1.images["wrist"][2]).permute(2, 0, 1))
    assert torch.equal(item["action"], torch.from_numpy(ep1.actions[2]))
    assert torch.equal(item["proprio"], torch.from_numpy(ep1.proprio[2]))
    assert item["instruction"] == ep1.meta.instruction and not item["action_is_pad"]
    assert item["success"].dtype == torch.bool


def test_frame_mode_batches_through_dataloader(episode_dir):
    ds = EpisodeDataset(episode_dir, cameras=["agentview"], mode="frame", step_extras=["mu"])
    batch = next(iter(DataLoader(ds, batch_size=4, shuffle=True, generator=torch.Generator().manual_seed(0))))
    assert batch["images"]["agentview"].shape == (4, 3, 32, 32)
    assert batch["action"].shape == (4, 7) and batch["extras"]["mu"].shape == (4, 7)
    assert len(batch["instruction"]) == 4 and "wrist" not in batch["images"]


def test_frame_mode_terminal_frame(episode_dir):
    ds = EpisodeDataset(episode_dir, mode="frame", include_terminal=True)
    assert len(ds) == 11 + 6 + 2
    last = ds[10]  # episode 0, frame T=10: success fires here, no action
    assert last["frame_index"] == 10 and last["action_is_pad"] and last["success"]
    assert torch.equal(last["action"], ds[9]["action"])  # edge padding
    zeros = EpisodeDataset(episode_dir, mode="frame", include_terminal=True, pad="zeros")
    assert torch.count_nonzero(zeros[10]["action"]) == 0


def test_chunk_mode_windows_and_padding(episode_dir):
    K = 4
    ds = EpisodeDataset(episode_dir, cameras=["agentview", "wrist"], mode="chunk", chunk=K, history=2)
    assert len(ds) == 10 + 5 + 1
    ep0 = read_episode(ds.paths[0])
    mid = ds[3]
    assert mid["actions"].shape == (K, 7) and not mid["action_is_pad"].any()
    assert torch.equal(mid["actions"], torch.from_numpy(ep0.actions[3:7]))
    assert mid["future_images"]["wrist"].shape == (K, 3, 32, 32)
    assert torch.equal(mid["future_images"]["wrist"], torch.from_numpy(ep0.images["wrist"][4:8]).permute(0, 3, 1, 2))
    assert torch.equal(mid["past_images"]["agentview"],
                       torch.from_numpy(ep0.images["agentview"][1:3]).permute(0, 3, 1, 2))
    assert not mid["past_is_pad"].any()

    end = ds[8]  # t=8 of T=10: actions 8, 9 real, then 2 pads; frames 9, 10 real, then 2 pads
    assert end["action_is_pad"].tolist() == [False, False, True, True]
    assert end["future_is_pad"].tolist() == [False, False, True, True]
    assert torch.equal(end["actions"][2], end["actions"][1])  # edge: repeat last real action
    assert torch.equal(end["future_images"]["wrist"][3], torch.from_numpy(ep0.images["wrist"][10]).permute(2, 0, 1))
    assert end["future_success"].tolist() == [False, True, True, True]

    start = ds[0]
    assert start["past_is_pad"].tolist() == [True, True]
    assert torch.equal(start["past_proprio"][0], torch.from_numpy(ep0.proprio[0]))

    one_step = ds[15]  # the 1-step episode
    assert one_step["action_is_pad"].tolist() == [False, True, True, True]


def test_chunk_mode_zero_padding(episode_dir):
    ds = EpisodeDataset(episode_dir, mode="chunk", chunk=4, pad="zeros", step_extras=["beta"])
    end = ds[8]
    assert torch.count_nonzero(end["actions"][2:]) == 0
    assert torch.count_nonzero(end["extras"]["beta"][2:]) == 0
    assert torch.count_nonzero(end["future_images"]["agentview"][2:]) == 0
    assert torch.count_nonzero(end["actions"][:2]) > 0
    batch = next(iter(DataLoader(ds, batch_size=5)))
    assert batch["actions"].shape == (5, 4, 7) and batch["action_is_pad"].shape == (5, 4)


def test_episode_mode(episode_dir):
    ds = EpisodeDataset(episode_dir, mode="episode", load_sim_state=True)
    assert len(ds) == 3
    item = ds[1]
    assert item["length"] == 5
    assert item["images"]["wrist"].shape == (6, 3, 32, 32)
    assert item["actions"].shape == (5, 7) and item["success"].shape == (6,)
    assert item["sim_state"].shape == (6, 9)
    assert ds.get_episode(1).length == 5


def test_compute_stats(episode_dir):
    ds = EpisodeDataset(episode_dir, mode="frame")
    stats = ds.compute_stats()
    eps = [read_episode(p) for p in ds.paths]
    proprio = np.concatenate([e.proprio for e in eps]).astype(np.float64)
    actions = np.concatenate([e.actions for e in eps]).astype(np.float64)
    assert stats["proprio"]["count"] == 11 + 6 + 2 and stats["action"]["count"] == 16
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(0), rtol=1e-6)
    np.testing.assert_array_equal(stats["action"]["min"], actions.min(0).astype(np.float32))
    np.testing.assert_array_equal(stats["action"]["max"], actions.max(0).astype(np.float32))
    np.testing.assert_allclose(stats["proprio"]["mean"], proprio.mean(0), rtol=1e-6)
    assert all(v.dtype == np.float32 for k, v in stats["action"].items() if k != "count")
    assert ds.compute_stats() is stats  # cached


def test_stats_refuse_non_finite_values(tmp_path, make_ep):
    write_episode(tmp_path / "nan.mcap", make_ep(special_floats=True))
    with pytest.raises(ValueError, match="non-finite.*nan.mcap"):
        EpisodeDataset(tmp_path).compute_stats()


def test_cache_reuses_decoded_episodes(episode_dir, monkeypatch):
    ds = EpisodeDataset(episode_dir, mode="frame")
    ds[0]
    import worldenv_core.data.dataset as mod

    monkeypatch.setattr(mod, "read_episode", lambda *a, **k: pytest.fail("episode decoded twice"))
    ds[1], ds[2]


def test_corrupt_and_inconsistent_inputs(tmp_path, episode_dir, make_ep, caplog):
    (episode_dir / "zz_bad.mcap").write_bytes(b"garbage")
    ds = EpisodeDataset(episode_dir)
    assert ds.num_episodes == 3 and "zz_bad.mcap" in caplog.text
    with pytest.raises(ValueError, match="zz_bad.mcap"):
        EpisodeDataset(episode_dir, on_error="raise")
    with pytest.raises(ValueError, match=r"cameras \['top'\] missing"):
        EpisodeDataset(episode_dir, cameras=["top"])
    write_episode(tmp_path / "big" / "a.mcap", make_ep(size=48))
    with pytest.raises(ValueError, match="image shapes"):
        EpisodeDataset([*ds.paths, tmp_path / "big" / "a.mcap"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no readable episode files"):
        EpisodeDataset(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="nothing_here"):
        EpisodeDataset(tmp_path / "nothing_here")
    with pytest.raises(ValueError, match="mode"):
        EpisodeDataset(episode_dir, mode="window")
