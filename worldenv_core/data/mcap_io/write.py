"""Writing episode files: atomically (a temporary name renamed when complete), one channel per chunk."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from worldenv_core.files import writing

from ..episode import Episode
from .format import (
    ACTION_TOPIC, CAMERA_PREFIX, JSON_SCHEMAS, METADATA_NAME, REAL_PREFIX, REFLECTOR_SCHEMA, REFLECTOR_TOPIC,
    SIM_STATE_TOPIC, STATE_TOPIC, meta_to_record, metadata_name,
)
from .png import encode_png


def _f64(a: np.ndarray) -> list:
    # float32 -> float64 is exact, and float64's repr is exact: the pair makes JSON lossless.
    return np.asarray(a, dtype=np.float64).tolist()


def _tmp_path(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


class _Channels:
    """Schemas registered once per file, channels per topic (a file may hold a second episode
    under a topic prefix, e.g. the real counterpart of an imagined rollout under `/real`)."""

    def __init__(self, writer: Writer):
        self.w, self.schemas, self.ids = writer, {}, {}

    def _schema(self, name: str, encoding: str, data: bytes) -> int:
        if name not in self.schemas:
            self.schemas[name] = self.w.register_schema(name, encoding, data)
        return self.schemas[name]

    def json(self, topic: str, schema: dict) -> None:
        sid = self._schema(schema["title"], "jsonschema", json.dumps(schema).encode())
        self.ids[topic] = self.w.register_channel(topic, "json", sid)

    def image(self, topic: str) -> None:
        sid = self._schema(CompressedImage.DESCRIPTOR.full_name, "protobuf",
                           build_file_descriptor_set(CompressedImage).SerializeToString())
        self.ids[topic] = self.w.register_channel(topic, "protobuf", sid)


def _register_episode(ch: _Channels, episode: Episode, prefix: str = "") -> None:
    for topic, schema in JSON_SCHEMAS.items():
        ch.json(prefix + topic, schema)
    for cam in episode.images:
        ch.image(prefix + CAMERA_PREFIX + cam)


def _write_messages(ch: _Channels, episode: Episode, png_level: int, prefix: str = "") -> None:
    """Every message of `episode`, grouped by channel with a chunk boundary after each."""
    w = ch.w
    ns = lambda t: int(round(t * 1e9 / episode.meta.fps))  # noqa: E731

    def put(topic: str, t: int, data: bytes) -> None:
        w.add_message(ch.ids[prefix + topic], log_time=ns(t), data=data, publish_time=ns(t), sequence=t)

    n = episode.num_frames
    proprio, joint = _f64(episode.proprio), _f64(episode.joint_pos)
    success = episode.success.tolist()
    for t in range(n):
        msg = {"frame": t, "proprio": proprio[t], "joint_pos": joint[t], "success": success[t]}
        put(STATE_TOPIC, t, json.dumps(msg).encode())
    w.flush()  # chunk boundary: one channel per chunk (see module docstring)
    actions = _f64(episode.actions)
    extras = {k: _f64(v) for k, v in episode.step_extras.items()}
    for t in range(episode.length):
        msg = {"frame": t, "action": actions[t], "extras": {k: v[t] for k, v in extras.items()}}
        put(ACTION_TOPIC, t, json.dumps(msg).encode())
    w.flush()
    sim = _f64(episode.sim_state)
    for t in range(n):
        put(SIM_STATE_TOPIC, t, json.dumps({"frame": t, "sim_state": sim[t]}).encode())
    w.flush()
    for cam, frames in episode.images.items():
        for t in range(n):
            s, nanos = divmod(ns(t), 10**9)
            msg = CompressedImage(frame_id=cam, data=encode_png(frames[t], png_level), format="png")
            msg.timestamp.seconds, msg.timestamp.nanos = s, nanos
            put(CAMERA_PREFIX + cam, t, msg.SerializeToString())
        w.flush()


@contextlib.contextmanager
def _atomic_writer(path: str | os.PathLike, chunk_size: int):
    """An MCAP writer on `<path>.tmp`, fsynced and renamed over `path` when the block completes.
    A crash or exception leaves no (new) file at `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    with writing(path, tmp):  # any failure removes the tmp; a full disk is one line naming the file
        with open(tmp, "wb") as f:
            w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            w.start(profile="", library="worldenv")
            yield w
            w.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)


def write_episode(path: str | os.PathLike, episode: Episode, *, png_level: int = 1,
                  chunk_size: int = 4 * 2**20) -> Path:
    """Write `episode` to `path` atomically: everything goes to `<path>.tmp`, which is fsynced
    and then renamed over `path`. A crash or exception leaves no (new) file at `path`, so a
    resumable collector can trust that every `*.mcap` it finds is complete."""
    with _atomic_writer(path, chunk_size) as w:
        ch = _Channels(w)
        _register_episode(ch, episode)
        _write_messages(ch, episode, png_level)
        w.add_metadata(METADATA_NAME, meta_to_record(episode))
    return Path(path)


def write_imagined_episode(path: str | os.PathLike, imagined: Episode, scores: dict[int, float] | None = None,
                           eta: float | None = None, real: Episode | None = None, *, png_level: int = 1,
                           chunk_size: int = 4 * 2**20) -> Path:
    """An imagined rollout in the same layout as a real episode (so `read_episode` and Foxglove
    read it alike), plus `/reflector` (the score at each scored frame, a plottable channel) when
    it was scored and, when the same actions were also run or recorded for real, that episode
    under `/real/...` (`read_episode(path, prefix="/real")`): imagined and real side by side."""
    scores = scores or {}
    if scores and eta is None:
        raise ValueError("reflector scores need the eta they are judged against")
    with _atomic_writer(path, chunk_size) as w:
        ch = _Channels(w)
        _register_episode(ch, imagined)
        if scores:
            ch.json(REFLECTOR_TOPIC, REFLECTOR_SCHEMA)
        if real is not None:
            _register_episode(ch, real, REAL_PREFIX)
        _write_messages(ch, imagined, png_level)
        for t, score in sorted(scores.items()):
            stamp = int(round(t * 1e9 / imagined.meta.fps))
            msg = {"frame": int(t), "score": float(score), "eta": float(eta), "stop": bool(score > eta)}
            w.add_message(ch.ids[REFLECTOR_TOPIC], log_time=stamp, publish_time=stamp, sequence=int(t),
                          data=json.dumps(msg).encode())
        if scores:
            w.flush()
        w.add_metadata(METADATA_NAME, meta_to_record(imagined))
        if real is not None:
            _write_messages(ch, real, png_level, REAL_PREFIX)
            w.add_metadata(metadata_name(REAL_PREFIX), meta_to_record(real))
    return Path(path)
