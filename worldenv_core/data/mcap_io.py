"""One episode per MCAP file: lossless, self-describing, and viewable in Foxglove.

File layout (schema_version 1):
  /camera/<name>  foxglove.CompressedImage (protobuf), PNG, frame_id = camera name   T+1 msgs
  /state          JSON {frame, proprio[7], joint_pos[7], success}                   T+1 msgs
  /sim_state      JSON {frame, sim_state[S]}                                        T+1 msgs
  /action         JSON {frame, action[7], extras: {name: nested list}}              T msgs
  metadata "episode": every EpisodeMeta field as a string, plus schema_version, length, dtypes,
                      shapes.
Every message carries log_time = publish_time = frame / fps (ns) and sequence = frame index;
the reader places messages by `sequence`, so rounding in the timestamps can never shuffle frames.

Why JSON for numbers: Foxglove plots JSON fields directly, and Python writes a float64 with the
shortest repr that parses back to the same bits, so float32 (widened to float64) and float64 both
round-trip bit-exactly. NaN/Infinity are written as the non-standard tokens Python's json accepts.

Why messages are grouped by channel (all /state, then /action, ..., each camera last) with a
chunk boundary between channels: MCAP's chunk index then lets a reader that asks for /state only
skip every image chunk, so loading proprio/actions for statistics does not decode a single PNG.
Foxglove reads through the index, so playback order is unaffected.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.reader import SeekingReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from .episode import ACTION_DIM, JOINT_DIM, PROPRIO_DIM, Episode, EpisodeMeta

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
METADATA_NAME = "episode"
STATE_TOPIC, SIM_STATE_TOPIC, ACTION_TOPIC = "/state", "/sim_state", "/action"
CAMERA_PREFIX = "/camera/"
SUFFIX = ".mcap"

try:  # cv2's PNG codec is ~2-3x faster than PIL's at the same (lossless) output
    import cv2

    cv2.setNumThreads(1)  # one image at a time; threads only add contention in data workers
except ImportError:  # pragma: no cover - cv2 ships with lerobot's deps, PIL is the fallback
    cv2 = None


class CorruptEpisodeError(ValueError):
    """An episode file that cannot be read back completely (truncated, garbage, missing data)."""

    def __init__(self, path: str | os.PathLike, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"corrupt episode file {self.path}: {reason}")

    def __reduce__(self):  # keep picklable across DataLoader worker processes
        return (type(self), (self.path, self.reason))


@dataclass
class EpisodeInfo:
    """What a file holds, read from its metadata record alone (no message is decoded)."""

    path: Path
    meta: EpisodeMeta
    length: int  # T (actions); the file has T+1 frames
    image_shapes: dict[str, tuple[int, int, int]]
    sim_state_dim: int
    step_extras: dict[str, tuple[int, ...]]  # name -> per-step shape


# --------------------------------------------------------------------------- images


def encode_png(img: np.ndarray, level: int = 1) -> bytes:
    """Lossless PNG of an RGB uint8 (H, W, 3) image. Level 1 with zlib's RLE strategy: measured on
    128 px rendered-like frames it was both the smallest and among the fastest (0.6 ms encode,
    0.2 ms decode), since deflate's longer match search buys little on rendered scenes."""
    if cv2 is not None:
        params = [cv2.IMWRITE_PNG_COMPRESSION, level, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
        ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise RuntimeError("cv2.imencode failed to encode a PNG")
        return buf.tobytes()
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(img).save(out, format="PNG", compress_level=level)
    return out.getvalue()


def decode_png(data: bytes, out: np.ndarray) -> None:
    """Decode a PNG into `out` (H, W, 3) uint8 RGB, checking the size matches."""
    if cv2 is not None:
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if bgr is None:
            raise ValueError("undecodable PNG")
        if bgr.shape != out.shape:
            raise ValueError(f"image is {bgr.shape}, metadata says {out.shape}")
        cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=out)
        return
    import io

    from PIL import Image

    arr = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    if arr.shape != out.shape:
        raise ValueError(f"image is {arr.shape}, metadata says {out.shape}")
    out[...] = arr


# --------------------------------------------------------------------------- schemas


def _num_array(n: int | None, description: str) -> dict:
    s: dict = {"type": "array", "items": {"type": "number"}, "description": description}
    if n is not None:
        s["minItems"] = s["maxItems"] = n
    return s


_FRAME = {"type": "integer", "description": "frame index t (0..T)"}
JSON_SCHEMAS = {
    STATE_TOPIC: {
        "title": "worldenv.State",
        "type": "object",
        "properties": {
            "frame": _FRAME,
            "proprio": _num_array(PROPRIO_DIM, "eef pos xyz, eef axis-angle xyz, gripper opening"),
            "joint_pos": _num_array(JOINT_DIM, "arm joint positions (rad)"),
            "success": {"type": "boolean", "description": "oracle success at this frame"},
        },
        "required": ["frame", "proprio", "joint_pos", "success"],
    },
    SIM_STATE_TOPIC: {
        "title": "worldenv.SimState",
        "type": "object",
        "properties": {"frame": _FRAME, "sim_state": _num_array(None, "MuJoCo flattened state")},
        "required": ["frame", "sim_state"],
    },
    ACTION_TOPIC: {
        "title": "worldenv.Action",
        "type": "object",
        "properties": {
            "frame": _FRAME,
            "action": _num_array(ACTION_DIM, "OSC_POSE delta (6) + gripper (-1 open, +1 close)"),
            "extras": {"type": "object", "description": "per-step policy outputs, e.g. mu, beta"},
        },
        "required": ["frame", "action"],
    },
}


def _f64(a: np.ndarray) -> list:
    # float32 -> float64 is exact, and float64's repr is exact: the pair makes JSON lossless.
    return np.asarray(a, dtype=np.float64).tolist()


def _meta_to_record(ep: Episode) -> dict[str, str]:
    m = ep.meta
    rec: dict[str, str] = {}
    for f in fields(EpisodeMeta):
        v = getattr(m, f.name)
        if f.name in ("cameras", "extra"):
            rec[f.name] = json.dumps(v)
        elif isinstance(v, bool):
            rec[f.name] = "true" if v else "false"
        else:
            rec[f.name] = repr(v) if isinstance(v, float) else str(v)
    rec["schema_version"] = str(SCHEMA_VERSION)
    rec["length"] = str(ep.length)
    rec["dtypes"] = json.dumps(
        {
            "images": "uint8",
            "proprio": ep.proprio.dtype.name,
            "joint_pos": ep.joint_pos.dtype.name,
            "sim_state": ep.sim_state.dtype.name,
            "success": "bool",
            "actions": ep.actions.dtype.name,
            "step_extras": {k: v.dtype.name for k, v in ep.step_extras.items()},
        }
    )
    rec["shapes"] = json.dumps(
        {
            "images": {c: list(v.shape[1:]) for c, v in ep.images.items()},
            "sim_state": [ep.sim_state.shape[1]],
            "step_extras": {k: list(v.shape[1:]) for k, v in ep.step_extras.items()},
        }
    )
    return rec


def _meta_from_record(rec: dict[str, str]) -> tuple[EpisodeMeta, int, dict, dict]:
    version = int(rec["schema_version"])
    if version > SCHEMA_VERSION:
        raise ValueError(f"schema_version {version} is newer than this reader ({SCHEMA_VERSION})")
    if rec["success"] not in ("true", "false"):
        raise ValueError(f"metadata success={rec['success']!r} is not 'true'/'false'")
    meta = EpisodeMeta(
        suite=rec["suite"],
        task_id=int(rec["task_id"]),
        task_name=rec["task_name"],
        instruction=rec["instruction"],
        init_state_index=int(rec["init_state_index"]),
        seed=int(rec["seed"]),
        source=rec["source"],
        success=rec["success"] == "true",
        attempts=int(rec["attempts"]),
        fps=float(rec["fps"]),
        cameras=list(json.loads(rec["cameras"])),
        extra=dict(json.loads(rec["extra"])),
    )
    return meta, int(rec["length"]), json.loads(rec["dtypes"]), json.loads(rec["shapes"])


# --------------------------------------------------------------------------- writing


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


def _metadata_name(prefix: str) -> str:
    return METADATA_NAME if not prefix else f"{prefix.strip('/')}_{METADATA_NAME}"


@contextlib.contextmanager
def _atomic_writer(path: str | os.PathLike, chunk_size: int):
    """An MCAP writer on `<path>.tmp`, fsynced and renamed over `path` when the block completes.
    A crash or exception leaves no (new) file at `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            w.start(profile="", library="worldenv")
            yield w
            w.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_episode(path: str | os.PathLike, episode: Episode, *, png_level: int = 1,
                  chunk_size: int = 4 * 2**20) -> Path:
    """Write `episode` to `path` atomically: everything goes to `<path>.tmp`, which is fsynced
    and then renamed over `path`. A crash or exception leaves no (new) file at `path`, so a
    resumable collector can trust that every `*.mcap` it finds is complete."""
    with _atomic_writer(path, chunk_size) as w:
        ch = _Channels(w)
        _register_episode(ch, episode)
        _write_messages(ch, episode, png_level)
        w.add_metadata(METADATA_NAME, _meta_to_record(episode))
    return Path(path)


REFLECTOR_TOPIC, REAL_PREFIX = "/reflector", "/real"
REFLECTOR_SCHEMA = {
    "title": "worldenv.ReflectorScore",
    "type": "object",
    "properties": {
        "frame": _FRAME,
        "score": {"type": "number", "description": "R(o_1:t, g): the reflector's probability that the task is done"},
        "eta": {"type": "number", "description": "the success threshold; the rollout stops when score > eta"},
        "stop": {"type": "boolean", "description": "score > eta: the imagined rollout ends here as a success"},
    },
    "required": ["frame", "score", "eta", "stop"],
}


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
        w.add_metadata(METADATA_NAME, _meta_to_record(imagined))
        if real is not None:
            _write_messages(ch, real, png_level, REAL_PREFIX)
            w.add_metadata(_metadata_name(REAL_PREFIX), _meta_to_record(real))
    return Path(path)


def read_reflector_scores(path: str | os.PathLike) -> dict[int, float]:
    """frame -> score of an imagined rollout's `/reflector` channel."""
    path = Path(path)
    with open(path, "rb") as f:
        reader = _open_reader(f, path)
        with _corruption_as_error(path, "cannot decode the reflector channel"):
            return {msg.sequence: json.loads(msg.data)["score"]
                    for _, _, msg in reader.iter_messages(topics=[REFLECTOR_TOPIC], log_time_order=False)}


# --------------------------------------------------------------------------- reading


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
    name = _metadata_name(prefix)
    with _corruption_as_error(path, "cannot read the metadata record"):
        recs = [m for m in reader.iter_metadata() if m.name == name]
        if not recs:
            raise CorruptEpisodeError(path, f"no '{name}' metadata record")
        meta, length, dtypes, shapes = _meta_from_record(recs[-1].metadata)
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

