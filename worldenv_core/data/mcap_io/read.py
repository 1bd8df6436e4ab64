"""Reading episode files: only the requested channels' chunks, every defect raised as a CorruptEpisodeError."""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.reader import SeekingReader

from ..episode import ACTION_DIM, JOINT_DIM, PROPRIO_DIM, Episode, EpisodeMeta
from .format import (
    ACTION_TOPIC, CAMERA_PREFIX, REFLECTOR_TOPIC, SIM_STATE_TOPIC, STATE_TOPIC, SUFFIX, CorruptEpisodeError,
    EpisodeInfo, meta_from_record, metadata_name,
)
from .png import decode_png

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _corruption_as_error(path: Path, what: str):
    """Turn whatever the mcap/protobuf/json/png layers raise on bad bytes into one error type
    that names the file. The underlying exception is chained for debugging."""
    try:
        yield
    except CorruptEpisodeError:
        raise
    except Exception as e:
        raise CorruptEpisodeError(path, f"{what}: {type(e).__name__}: {e}") from e


_MAGIC = b"\x89MCAP0\r\n"


def _open_reader(f, path: Path) -> SeekingReader:
    if f.seek(0, os.SEEK_END) == 0:
        raise CorruptEpisodeError(path, "empty file (0 bytes)")
    f.seek(0)
    with _corruption_as_error(path, "not a readable MCAP file"):
        reader = SeekingReader(f, validate_crcs=True)
    # A file cut short (killed writer, full disk, partial copy) lacks the closing magic; saying
    # so beats the record-parsing error the reader would hit somewhere in the middle.
    size = f.seek(0, os.SEEK_END)
    f.seek(size - len(_MAGIC))
    if f.read(len(_MAGIC)) != _MAGIC:
        raise CorruptEpisodeError(path, f"truncated: {size} bytes and no MCAP end magic (interrupted write?)")
    f.seek(0)
    return reader


def _read_info(reader: SeekingReader, path: Path, prefix: str = "") -> EpisodeInfo:
    name = metadata_name(prefix)
    with _corruption_as_error(path, "cannot read the metadata record"):
        recs = [m for m in reader.iter_metadata() if m.name == name]
        if not recs:
            raise CorruptEpisodeError(path, f"no '{name}' metadata record")
        meta, length, dtypes, shapes = meta_from_record(recs[-1].metadata)
    img_shapes = {c: tuple(int(x) for x in s) for c, s in shapes["images"].items()}
    if list(img_shapes) != meta.cameras:
        raise CorruptEpisodeError(path, f"metadata image shapes {list(img_shapes)} != cameras {meta.cameras}")
    return EpisodeInfo(
        path=path, meta=meta, length=length, image_shapes=img_shapes,
        sim_state_dim=int(shapes["sim_state"][0]),
        step_extras={k: tuple(int(x) for x in s) for k, s in shapes["step_extras"].items()},
    )


def read_info(path: str | os.PathLike) -> EpisodeInfo:
    """Metadata, length and shapes of an episode file, without decoding any message."""
    path = Path(path)
    with open(path, "rb") as f:
        return _read_info(_open_reader(f, path), path)


def read_meta(path: str | os.PathLike) -> EpisodeMeta:
    return read_info(path).meta


def read_episode(path: str | os.PathLike, cameras: list[str] | None = None,
                 load_sim_state: bool = True, prefix: str = "") -> Episode:
    """Read an episode. `cameras=None` loads every camera, `[]` none; unknown camera names raise
    ValueError. Without sim_state the episode gets a (T+1, 0) array. Only the chunks of the
    requested channels are read and decompressed. Damaged files raise CorruptEpisodeError.
    `prefix="/real"` reads the real counterpart stored beside an imagined rollout."""
    path = Path(path)
    with open(path, "rb") as f:
        reader = _open_reader(f, path)
        info = _read_info(reader, path, prefix)
        meta = info.meta
        if cameras is None:
            cameras = list(meta.cameras)
        missing = [c for c in cameras if c not in meta.cameras]
        if missing:
            raise ValueError(f"{path}: cameras {missing} not in file (it has {meta.cameras})")
        T, n = info.length, info.length + 1

        proprio = np.zeros((n, PROPRIO_DIM), np.float64)
        joint = np.zeros((n, JOINT_DIM), np.float64)
        success = np.zeros(n, np.bool_)
        actions = np.zeros((T, ACTION_DIM), np.float64)
        extras = {k: np.zeros((T, *s), np.float64) for k, s in info.step_extras.items()}
        sim = np.zeros((n, info.sim_state_dim if load_sim_state else 0), np.float64)
        images = {c: np.zeros((n, *info.image_shapes[c]), np.uint8) for c in cameras}
        expected = {STATE_TOPIC: n, ACTION_TOPIC: T, **{CAMERA_PREFIX + c: n for c in cameras}}
        if load_sim_state:
            expected[SIM_STATE_TOPIC] = n
        seen = {topic: np.zeros(k, np.bool_) for topic, k in expected.items()}

        with _corruption_as_error(path, "cannot decode messages"):
            for _, channel, msg in reader.iter_messages(topics=[prefix + t for t in expected], log_time_order=False):
                topic, t = channel.topic[len(prefix):], msg.sequence
                if t >= expected[topic] or seen[topic][t]:
                    raise CorruptEpisodeError(path, f"{topic}: unexpected or duplicate frame {t}")
                seen[topic][t] = True
                if topic.startswith(CAMERA_PREFIX):
                    img = CompressedImage.FromString(msg.data)
                    if img.format != "png":
                        raise CorruptEpisodeError(path, f"{topic}: image format {img.format!r}, expected 'png'")
                    decode_png(img.data, images[topic[len(CAMERA_PREFIX):]][t])
                    continue
                d = json.loads(msg.data)
                if topic == STATE_TOPIC:
                    proprio[t], joint[t], success[t] = d["proprio"], d["joint_pos"], d["success"]
                elif topic == ACTION_TOPIC:
                    actions[t] = d["action"]
                    for k in extras:
                        extras[k][t] = d["extras"][k]
                else:
                    sim[t] = d["sim_state"]
        for topic, mask in seen.items():
            if not mask.all():
                lost = np.flatnonzero(~mask)
                raise CorruptEpisodeError(
                    path, f"{topic}: {len(lost)} of {len(mask)} frames missing (first: {int(lost[0])})"
                )

    meta.cameras = list(cameras)  # the Episode describes what was loaded
    with _corruption_as_error(path, "inconsistent contents"):
        return Episode(
            meta=meta, images=images, proprio=proprio.astype(np.float32), joint_pos=joint,
            sim_state=sim, success=success, actions=actions.astype(np.float32),
            step_extras={k: v.astype(np.float32) for k, v in extras.items()},
        )


def list_episode_files(paths_or_dir: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Path]:
    """A directory (searched recursively for *.mcap, sorted), one file, or an iterable of files.
    `*.mcap.tmp` leftovers of interrupted writes never match."""
    if isinstance(paths_or_dir, (str, os.PathLike)):
        p = Path(paths_or_dir)
        if p.is_dir():
            return sorted(q for q in p.rglob("*" + SUFFIX) if q.is_file())
        if not p.exists():
            raise FileNotFoundError(f"no episode file or directory at {p}")
        return [p]
    return [Path(p) for p in paths_or_dir]


def glob_episode_files(patterns: Iterable[str]) -> list[Path]:
    """The recorded episodes matching shell patterns (the analysis tools' `--episodes`), sorted."""
    import glob

    return sorted(Path(p) for pattern in patterns for p in glob.glob(pattern))


def iter_episodes(paths_or_dir, on_error: str = "skip", **read_kwargs) -> Iterator[Episode]:
    """Yield the episodes of a directory or list of files. With on_error="skip", a corrupt file
    is logged (warning naming the file and the problem) and skipped; "raise" re-raises."""
    if on_error not in ("skip", "raise"):
        raise ValueError(f"on_error must be 'skip' or 'raise', got {on_error!r}")
    for p in list_episode_files(paths_or_dir):
        try:
            ep = read_episode(p, **read_kwargs)
        except CorruptEpisodeError as e:
            if on_error == "raise":
                raise
            log.warning("skipping %s", e)
            continue
        yield ep


def read_reflector_scores(path: str | os.PathLike) -> dict[int, float]:
    """frame -> score of an imagined rollout's `/reflector` channel."""
    path = Path(path)
    with open(path, "rb") as f:
        reader = _open_reader(f, path)
        with _corruption_as_error(path, "cannot decode the reflector channel"):
            return {msg.sequence: json.loads(msg.data)["score"]
                    for _, _, msg in reader.iter_messages(topics=[REFLECTOR_TOPIC], log_time_order=False)}
