import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

import worldenv_core.data.mcap_io.write as mcap_write
from worldenv_core.data.episode import episode_differences
from worldenv_core.data.mcap_io import (
    CorruptEpisodeError,
    read_episode,
    read_reflector_scores,
    write_episode,
    write_imagined_episode,
)


def test_round_trip_is_bit_exact(tmp_path, episode):
    path = write_episode(tmp_path / "ep.mcap", episode)
    back = read_episode(path)
    assert episode_differences(episode, back) == []
    assert back.meta == episode.meta  # every metadata field, including extra and cameras
    # spot-check the special floats survived as the same bits
    assert np.signbit(back.proprio[0, 0]) and back.proprio[0, 1] == np.float32(1e-45)
    assert np.isnan(back.proprio[0, 5]) and back.joint_pos[1, 1] == 5e-324
    assert back.step_extras["chunk_logp"].shape == (10, 2, 3)


def test_zero_step_episode_round_trips(tmp_path, make_ep):
    ep = make_ep(T=0, extras=False)
    back = read_episode(write_episode(tmp_path / "ep.mcap", ep))
    assert episode_differences(ep, back) == []


def test_file_layout_is_foxglove_compatible(tmp_path, episode):
    path = write_episode(tmp_path / "ep.mcap", episode)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        chunk_compressions = {c.compression for c in summary.chunk_indexes}
        assert chunk_compressions == {"zstd"}
        topics = {ch.topic: ch for ch in summary.channels.values()}
        assert set(topics) == {"/camera/agentview", "/camera/wrist", "/state", "/sim_state", "/action"}
        for t in ("/state", "/sim_state", "/action"):
            assert topics[t].message_encoding == "json"
            assert summary.schemas[topics[t].schema_id].encoding == "jsonschema"
        img_schema = summary.schemas[topics["/camera/wrist"].schema_id]
        assert (img_schema.name, img_schema.encoding) == ("foxglove.CompressedImage", "protobuf")
        counts = {topics_name: 0 for topics_name in topics}
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=["/camera/wrist"]):
            t = message.sequence
            assert decoded.format == "png" and decoded.frame_id == "wrist"
            assert decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos == message.log_time
            assert message.log_time == round(t / 20.0 * 1e9)
            counts["/camera/wrist"] += 1
        assert counts["/camera/wrist"] == 11
        actions = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/action"])]
        assert len(actions) == 10 and sorted(a["frame"] for a in actions) == list(range(10))
        assert set(actions[0]["extras"]) == {"mu", "beta", "chunk_logp"}
        (meta,) = list(reader.iter_metadata())
        assert meta.name == "episode"
        assert meta.metadata["schema_version"] == "1" and meta.metadata["length"] == "10"
        assert json.loads(meta.metadata["dtypes"])["proprio"] == "float32"
        assert all(isinstance(v, str) for v in meta.metadata.values())


def test_failed_write_leaves_no_final_file(tmp_path, episode, monkeypatch):
    path = tmp_path / "ep.mcap"
    calls = []

    def exploding_encode(img, level=1):
        calls.append(1)
        if len(calls) > 3:
            raise RuntimeError("disk on fire")
        return b"not really a png"

    monkeypatch.setattr(mcap_write, "encode_png", exploding_encode)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_episode(path, episode)
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []  # the .tmp is cleaned up too


def test_failed_overwrite_keeps_previous_file(tmp_path, episode, make_ep, monkeypatch):
    path = write_episode(tmp_path / "ep.mcap", episode)
    before = path.read_bytes()
    monkeypatch.setattr(mcap_write, "encode_png", lambda img, level=1: (_ for _ in ()).throw(OSError("full")))
    with pytest.raises(OSError):
        write_episode(path, make_ep(seed=5))
    assert path.read_bytes() == before


# ------------------------------------------------------------------ imagined rollouts

LAYOUT = __import__("pathlib").Path(__file__).resolve().parents[4] / "foxglove" / "imagined_vs_real.json"


def _layout_topics() -> set[str]:
    """Every topic the Foxglove layout's panels read (image topics, and plot paths up to the field)."""
    cfg = json.loads(LAYOUT.read_text())["configById"]
    topics = {c["imageMode"]["imageTopic"] for k, c in cfg.items() if k.startswith("Image!")}
    topics |= {p["value"].split(".")[0] for k, c in cfg.items() if k.startswith("Plot!") for p in c["paths"]}
    return topics


def test_an_imagined_rollout_reads_back_beside_its_real_counterpart(tmp_path, make_ep):
    real = make_ep(T=8, cameras=("agentview",), seed=1)
    imagined = make_ep(T=8, cameras=("agentview",), seed=2, sim_dim=0)
    imagined.meta.source = "imagined"
    scores = {0: 0.1, 4: 0.4, 8: 0.9}
    path = write_imagined_episode(tmp_path / "r.mcap", imagined, scores, eta=0.5, real=real)
    assert episode_differences(imagined, read_episode(path)) == []  # the same layout as any episode
    assert episode_differences(real, read_episode(path, prefix="/real")) == []
    assert read_reflector_scores(path) == scores
    with open(path, "rb") as f:
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        stops = [json.loads(m.data)["stop"] for _, c, m in reader.iter_messages(topics=["/reflector"])]
    assert stops == [False, False, True]
    assert _layout_topics() <= topics, f"the layout reads topics the file lacks: {_layout_topics() - topics}"


def test_an_unscored_imagined_replay_has_no_reflector_channel_and_scores_need_eta(tmp_path, make_ep):
    ep = make_ep(T=4, cameras=("agentview",))
    path = write_imagined_episode(tmp_path / "r.mcap", ep)
    assert read_reflector_scores(path) == {}
    with pytest.raises(CorruptEpisodeError, match="real_episode"):
        read_episode(path, prefix="/real")
    with pytest.raises(ValueError, match="eta"):
        write_imagined_episode(tmp_path / "s.mcap", ep, {0: 0.3})
