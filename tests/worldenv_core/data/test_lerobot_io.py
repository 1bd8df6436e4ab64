import json
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # before lerobot/huggingface_hub read it

import numpy as np
import pytest

from worldenv_core.data.episode import Episode
from worldenv_core.data.lerobot_io import export_lerobot, import_lerobot, libero_state8_to_proprio
from worldenv_core.data.mcap_io import write_episode

REPO = "local/worldenv_test"


@pytest.fixture
def two_episodes(make_ep):
    return [make_ep(T=10, seed=0, task_id=1), make_ep(T=6, seed=1, task_id=2)]


def _check_same(orig: Episode, back: Episode):
    assert back.length == orig.length
    for c in orig.images:
        assert np.array_equal(back.images[c], orig.images[c]), c
    assert back.proprio.tobytes() == orig.proprio.tobytes()
    assert back.actions.tobytes() == orig.actions.tobytes()
    assert np.array_equal(back.success, orig.success)
    assert back.meta.source == "import" and back.meta.extra["original_source"] == orig.meta.source
    for field in ("suite", "task_id", "task_name", "instruction", "init_state_index", "seed", "success",
                  "attempts", "fps", "cameras"):
        assert getattr(back.meta, field) == getattr(orig.meta, field), field
    assert np.isnan(back.joint_pos).all() and back.sim_state.shape == (orig.num_frames, 0)


def test_export_import_round_trip(tmp_path, two_episodes):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = export_lerobot(two_episodes, tmp_path / "lr", REPO)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"].startswith("v3") and info["fps"] == 20
    assert info["total_episodes"] == 2 and info["total_frames"] == 11 + 7
    assert not (tmp_path / "lr.partial").exists()
    ds = LeRobotDataset(REPO, root=root)
    assert {"observation.images.agentview", "observation.images.wrist", "observation.state", "action"} <= set(
        ds.features)
    assert ds.features["observation.state"]["shape"] in ((7,), [7])
    assert ds[0]["task"] == two_episodes[0].meta.instruction

    back = list(import_lerobot(root, REPO))
    assert len(back) == 2
    for orig, b in zip(two_episodes, back):
        _check_same(orig, b)
    only_wrist = next(import_lerobot(root, REPO, cameras=["wrist"], episodes=[1]))
    assert list(only_wrist.images) == ["wrist"] and only_wrist.length == 6


def test_export_from_mcap_files(tmp_path, two_episodes):
    for i, ep in enumerate(two_episodes):
        write_episode(tmp_path / "mcap" / f"ep{i}.mcap", ep)
    root = export_lerobot(tmp_path / "mcap", tmp_path / "lr", REPO, fps=20)
    back = list(import_lerobot(root, REPO))
    for orig, b in zip(two_episodes, back):
        _check_same(orig, b)
    with pytest.raises(FileExistsError):
        export_lerobot(two_episodes, root, REPO)


def test_import_foreign_libero_layout(tmp_path):
    """A LIBERO conversion: other camera keys, 8-D state, one action per frame, no success."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(0)
    feats = {
        "observation.images.image": {"dtype": "image", "shape": (16, 16, 3), "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (8,), "names": None},
        "action": {"dtype": "float32", "shape": (7,), "names": None},
    }
    root = tmp_path / "libero"
    ds = LeRobotDataset.create("local/libero", fps=10, features=feats, root=root, use_videos=False)
    frames = []
    for _ in range(5):
        f = {"observation.images.image": rng.integers(0, 256, (16, 16, 3), dtype=np.uint8),
             "observation.state": rng.standard_normal(8).astype(np.float32),
             "action": rng.standard_normal(7).astype(np.float32), "task": "open the drawer"}
        frames.append(f)
        ds.add_frame(f)
    ds.save_episode()
    ds.finalize()

    with pytest.raises(KeyError, match="images.agentview"):
        next(import_lerobot(root, "local/libero", cameras=["agentview"]))
    (ep,) = import_lerobot(root, "local/libero", suite="libero_goal",
                           key_map={"images.agentview": "observation.images.image"}, cameras=["agentview"])
    assert ep.meta.source == "import" and ep.meta.suite == "libero_goal" and ep.meta.fps == 10.0
    assert ep.meta.instruction == "open the drawer" and ep.meta.init_state_index == -1
    assert ep.length == 4  # 5 frames, the last action has no resulting frame and is dropped
    assert np.array_equal(ep.images["agentview"][3], frames[3]["observation.images.image"])
    assert np.array_equal(ep.actions, np.stack([f["action"] for f in frames[:4]]))
    state = np.stack([f["observation.state"] for f in frames])
    assert np.array_equal(ep.proprio, libero_state8_to_proprio(state))
    assert ep.success.tolist() == [False] * 4 + [True]

    flipped = next(import_lerobot(root, "local/libero", key_map={"images.agentview": "observation.images.image"},
                                  cameras=["agentview"], image_fn=lambda cam, x: x[:, ::-1, ::-1]))
    assert np.array_equal(flipped.images["agentview"][0], frames[0]["observation.images.image"][::-1, ::-1])


def test_video_export_imports_back_as_uint8(tmp_path, make_ep):
    """mp4 is lossy, so only shape/dtype and closeness on a smooth image are checked."""
    ep = make_ep(T=4, cameras=("agentview",))
    y, x = np.mgrid[0:32, 0:32]
    smooth = np.stack([x * 8, y * 8, (x + y) * 4], -1).astype(np.uint8)
    ep.images["agentview"][:] = smooth
    root = export_lerobot([ep], tmp_path / "lrv", REPO, use_videos=True)
    (back,) = import_lerobot(root, REPO)
    img = back.images["agentview"]
    assert img.dtype == np.uint8 and img.shape == (5, 32, 32, 3)
    assert np.abs(img.astype(int) - smooth.astype(int)).mean() < 12
    assert back.actions.tobytes() == ep.actions.tobytes()
