import logging
import pickle

import numpy as np
import pytest

from worldenv_core.data.mcap_io import (
    CorruptEpisodeError,
    iter_episodes,
    list_episode_files,
    read_episode,
    read_info,
    write_episode,
)


def test_partial_reads(tmp_path, episode):
    path = write_episode(tmp_path / "ep.mcap", episode)
    back = read_episode(path, cameras=["wrist"], load_sim_state=False)
    assert list(back.images) == ["wrist"] and back.meta.cameras == ["wrist"]
    assert np.array_equal(back.images["wrist"], episode.images["wrist"])
    assert back.sim_state.shape == (11, 0)
    none = read_episode(path, cameras=[])
    assert none.images == {} and np.array_equal(none.actions, episode.actions, equal_nan=True)
    with pytest.raises(ValueError, match=r"cameras \['top'\] not in file"):
        read_episode(path, cameras=["top"])


def test_read_info_needs_no_decoding(tmp_path, episode):
    info = read_info(write_episode(tmp_path / "ep.mcap", episode))
    assert info.length == 10 and info.meta == episode.meta
    assert info.image_shapes == {"agentview": (32, 32, 3), "wrist": (32, 32, 3)}
    assert info.sim_state_dim == 9 and info.step_extras["chunk_logp"] == (2, 3)


def _truncated(tmp_path, episode):
    good = write_episode(tmp_path / "good.mcap", episode)
    data = good.read_bytes()
    bad = tmp_path / "truncated.mcap"
    bad.write_bytes(data[: len(data) // 2])
    return bad


def _garbage(tmp_path):
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(np.random.default_rng(0).bytes(5000))
    return bad


def _bitflip(tmp_path, episode):
    good = write_episode(tmp_path / "good2.mcap", episode)
    data = bytearray(good.read_bytes())
    # flip bytes inside the first chunk (the /state messages): only the CRC can notice
    data[200:210] = bytes(b ^ 0xFF for b in data[200:210])
    bad = tmp_path / "bitflip.mcap"
    bad.write_bytes(bytes(data))
    return bad


@pytest.mark.parametrize("kind", ["truncated", "garbage", "empty", "bitflip"])
def test_corrupt_files_raise_naming_the_file(tmp_path, episode, kind):
    if kind == "truncated":
        bad = _truncated(tmp_path, episode)
    elif kind == "garbage":
        bad = _garbage(tmp_path)
    elif kind == "bitflip":
        bad = _bitflip(tmp_path, episode)
    else:
        bad = tmp_path / "empty.mcap"
        bad.write_bytes(b"")
    with pytest.raises(CorruptEpisodeError) as ei:
        read_episode(bad)
    assert str(bad) in str(ei.value) and ei.value.path == str(bad)
    assert isinstance(ei.value, ValueError) and ei.value.reason
    expected_reason = {"truncated": "truncated", "bitflip": "crc", "garbage": "magic", "empty": "empty"}[kind]
    assert expected_reason in ei.value.reason.lower()


def test_missing_file_is_not_corruption(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_episode(tmp_path / "nope.mcap")


def test_error_pickles_for_dataloader_workers():
    e = pickle.loads(pickle.dumps(CorruptEpisodeError("/x/y.mcap", "bad footer")))
    assert e.path == "/x/y.mcap" and "bad footer" in str(e)


def test_iter_episodes_skips_corrupt_files(tmp_path, make_ep, caplog):
    d = tmp_path / "eps"
    eps = [make_ep(T=3 + i, seed=i) for i in range(3)]
    for i, ep in enumerate(eps):
        write_episode(d / f"ep_{i}.mcap", ep)
    bad1 = _truncated(d, make_ep(seed=9))
    bad2 = _garbage(d)
    (d / "ep_9.mcap.tmp").write_bytes(b"half written")  # an interrupted write: never listed
    (d / "good.mcap").unlink()  # helper byproduct of _truncated
    with caplog.at_level(logging.WARNING, logger="worldenv_core.data.mcap_io"):
        loaded = list(iter_episodes(d))
    assert len(loaded) == 3
    assert sorted(ep.length for ep in loaded) == [3, 4, 5]
    warned = " ".join(r.getMessage() for r in caplog.records)
    assert str(bad1) in warned and str(bad2) in warned
    with pytest.raises(CorruptEpisodeError):
        list(iter_episodes(d, on_error="raise"))
    # a list of files, and keyword passthrough
    light = list(iter_episodes([d / "ep_0.mcap", d / "ep_1.mcap"], cameras=[], load_sim_state=False))
    assert [ep.images for ep in light] == [{}, {}]


def test_list_episode_files(tmp_path, episode_dir):
    (episode_dir / "sub").mkdir()
    (episode_dir / "sub" / "x.mcap.tmp").write_bytes(b"")
    files = list_episode_files(episode_dir)
    assert [f.name for f in files] == ["ep_000.mcap", "ep_001.mcap", "ep_002.mcap"]
    assert list_episode_files(files[0]) == [files[0]]
