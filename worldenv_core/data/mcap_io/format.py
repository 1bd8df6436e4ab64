"""What an episode file holds: topics, JSON schemas, the metadata record and the errors a reader raises."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, fields
from pathlib import Path

from ..episode import ACTION_DIM, JOINT_DIM, PROPRIO_DIM, Episode, EpisodeMeta

SCHEMA_VERSION = 1
METADATA_NAME = "episode"
STATE_TOPIC, SIM_STATE_TOPIC, ACTION_TOPIC = "/state", "/sim_state", "/action"
CAMERA_PREFIX = "/camera/"
SUFFIX = ".mcap"


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


def _num_array(n: int | None, description: str) -> dict:
    s: dict = {"type": "array", "items": {"type": "number"}, "description": description}
    if n is not None:
        s["minItems"] = s["maxItems"] = n
    return s


FRAME_FIELD = {"type": "integer", "description": "frame index t (0..T)"}
JSON_SCHEMAS = {
    STATE_TOPIC: {
        "title": "worldenv.State",
        "type": "object",
        "properties": {
            "frame": FRAME_FIELD,
            "proprio": _num_array(PROPRIO_DIM, "eef pos xyz, eef axis-angle xyz, gripper opening"),
            "joint_pos": _num_array(JOINT_DIM, "arm joint positions (rad)"),
            "success": {"type": "boolean", "description": "oracle success at this frame"},
        },
        "required": ["frame", "proprio", "joint_pos", "success"],
    },
    SIM_STATE_TOPIC: {
        "title": "worldenv.SimState",
        "type": "object",
        "properties": {"frame": FRAME_FIELD, "sim_state": _num_array(None, "MuJoCo flattened state")},
        "required": ["frame", "sim_state"],
    },
    ACTION_TOPIC: {
        "title": "worldenv.Action",
        "type": "object",
        "properties": {
            "frame": FRAME_FIELD,
            "action": _num_array(ACTION_DIM, "OSC_POSE delta (6) + gripper (-1 open, +1 close)"),
            "extras": {"type": "object", "description": "per-step policy outputs, e.g. mu, beta"},
        },
        "required": ["frame", "action"],
    },
}


def meta_to_record(ep: Episode) -> dict[str, str]:
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


def meta_from_record(rec: dict[str, str]) -> tuple[EpisodeMeta, int, dict, dict]:
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


def metadata_name(prefix: str) -> str:
    return METADATA_NAME if not prefix else f"{prefix.strip('/')}_{METADATA_NAME}"


REFLECTOR_TOPIC, REAL_PREFIX = "/reflector", "/real"
REFLECTOR_SCHEMA = {
    "title": "worldenv.ReflectorScore",
    "type": "object",
    "properties": {
        "frame": FRAME_FIELD,
        "score": {"type": "number", "description": "R(o_1:t, g): the reflector's probability that the task is done"},
        "eta": {"type": "number", "description": "the success threshold; the rollout stops when score > eta"},
        "stop": {"type": "boolean", "description": "score > eta: the imagined rollout ends here as a success"},
    },
    "required": ["frame", "score", "eta", "stop"],
}
