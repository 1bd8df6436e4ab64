"""Export episodes to a LeRobotDataset v3, and import LIBERO demonstrations from one.

LeRobot stores one action per frame, our episodes have T+1 frames and T actions. Export keeps all
T+1 frames (the terminal frame is where success fires) and marks the terminal frame's action as
padding (`action_is_pad`, action = zeros). Import drops that padded action again, so our own
exports round-trip exactly; a foreign dataset (one action per frame, no terminal frame) becomes
N frames and N-1 actions: the state after the last action was never recorded, and inventing a
frame would be worse than dropping one action.

The EpisodeMeta of every exported episode goes to `meta/worldenv_episodes.jsonl` beside
LeRobot's own metadata (LeRobot has no place for per-episode seeds or init-state indices);
import restores it when present. joint_pos and sim_state are not exported (the MCAP files are
the lossless store): imported episodes get NaN joint_pos and a (T+1, 0) sim_state.

Everything here works offline: the dataset is created and read through `root`, never the hub.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterable, Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

from worldenv_core.robot import gripper_opening

from .episode import ACTION_DIM, JOINT_DIM, PROPRIO_DIM, Episode, EpisodeMeta
from .mcap_io import list_episode_files, read_episode

log = logging.getLogger(__name__)

IMAGE_PREFIX = "observation.images."
STATE_KEY, ACTION_KEY, SUCCESS_KEY, PAD_KEY = "observation.state", "action", "success", "action_is_pad"
EPISODE_META_FILE = "meta/worldenv_episodes.jsonl"
STATE_NAMES = ["eef_x", "eef_y", "eef_z", "eef_ax", "eef_ay", "eef_az", "gripper"]
ACTION_NAMES = ["dx", "dy", "dz", "dax", "day", "daz", "gripper"]


def _lerobot_dataset():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # nothing may be fetched at run time here
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset


@lru_cache(maxsize=1)
def video_backend() -> str:
    """The video decoder LeRobot should use here: torchcodec when its FFmpeg libraries load, else
    pyav (bundled with its own FFmpeg). Chosen once with a one-line notice, because left to itself
    lerobot logs torchcodec's ~40-line loading traceback every time it looks."""
    try:
        import torchcodec  # noqa: F401
    except (ImportError, OSError, RuntimeError):
        log.info("torchcodec cannot load its FFmpeg libraries here; LeRobot video decoding uses pyav")
        return "pyav"
    return "torchcodec"


def _iter_input(episodes_or_paths) -> Iterator[Episode]:
    if isinstance(episodes_or_paths, Episode):
        yield episodes_or_paths
        return
    if isinstance(episodes_or_paths, (str, os.PathLike)):
        episodes_or_paths = list_episode_files(episodes_or_paths)
    for item in episodes_or_paths:
        yield item if isinstance(item, Episode) else read_episode(item, load_sim_state=False)


def export_lerobot(episodes_or_paths: Episode | Iterable[Episode | str | os.PathLike] | str | os.PathLike,
                   root: str | os.PathLike, repo_id: str, fps: int | None = None, *,
                   cameras: list[str] | None = None, use_videos: bool = False,
                   robot_type: str = "panda") -> Path:
    """Write episodes (objects, MCAP files or a directory of them) as a LeRobotDataset v3 at `root`.

    Features: observation.images.<cam> (HWC uint8; PNG images, or mp4 when use_videos=True, which
    is lossy), observation.state (7), action (7), success (1, bool), action_is_pad (1, bool),
    plus the task string (the instruction). `fps` defaults to the first episode's. `root` must
    not exist; the dataset is built in `<root>.partial` and renamed when complete.
    """
    root = Path(root)
    if root.exists():
        raise FileExistsError(f"LeRobot export target {root} already exists")
    partial = root.with_name(root.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)  # leftover of an interrupted export
    it = _iter_input(episodes_or_paths)
    first = next(it, None)
    if first is None:
        raise ValueError("export_lerobot: no episodes to export")
    cams = list(first.meta.cameras) if cameras is None else list(cameras)
    if missing := [c for c in cams if c not in first.images]:
        raise ValueError(f"export_lerobot: first episode lacks cameras {missing} (has {list(first.images)})")
    fps_val = first.meta.fps if fps is None else fps
    if float(fps_val) != int(fps_val):
        raise ValueError(f"LeRobot needs an integer fps, got {fps_val}")
    fps_val = int(fps_val)

    features = {
        **{
            IMAGE_PREFIX + c: {"dtype": "video" if use_videos else "image", "shape": first.images[c].shape[1:],
                               "names": ["height", "width", "channels"]}
            for c in cams
        },
        STATE_KEY: {"dtype": "float32", "shape": (PROPRIO_DIM,), "names": STATE_NAMES},
        ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,), "names": ACTION_NAMES},
        SUCCESS_KEY: {"dtype": "bool", "shape": (1,), "names": None},
        PAD_KEY: {"dtype": "bool", "shape": (1,), "names": None},
    }
    from datasets.utils.logging import disable_progress_bar

    disable_progress_bar()  # two "Map" bars per episode from Hugging Face datasets: noise in our logs
    ds = _lerobot_dataset().create(repo_id, fps=fps_val, features=features, root=partial,
                                   robot_type=robot_type, use_videos=use_videos, video_backend=video_backend())
    metas = []
    try:
        for ep in _chain(first, it):
            missing = [c for c in cams if c not in ep.images]
            if missing:
                raise ValueError(f"episode {len(metas)} ({ep.meta.task_name}) lacks cameras {missing}")
            T = ep.length
            zero = np.zeros(ACTION_DIM, np.float32)
            for t in range(T + 1):
                frame = {IMAGE_PREFIX + c: ep.images[c][t] for c in cams}
                frame[STATE_KEY] = ep.proprio[t]
                frame[ACTION_KEY] = ep.actions[t] if t < T else zero
                frame[SUCCESS_KEY] = np.array([ep.success[t]])
                frame[PAD_KEY] = np.array([t >= T])
                frame["task"] = ep.meta.instruction
                ds.add_frame(frame)
            ds.save_episode()
            metas.append({"episode_index": len(metas), **dataclasses.asdict(ep.meta)})
    finally:
        ds.finalize()
    with open(partial / EPISODE_META_FILE, "w") as f:
        for m in metas:
            f.write(json.dumps(m) + "\n")
    os.replace(partial, root)
    return root


def _chain(first, rest):
    yield first
    yield from rest


def libero_state8_to_proprio(state: np.ndarray) -> np.ndarray:
    """LIBERO LeRobot/RLDS conversions store an 8-D state: eef pos (3), eef axis-angle (3) and the
    two finger joint positions. Our proprio's last entry is the gripper opening in [0, 1], the
    same function of the finger joints that the env uses."""
    state = np.asarray(state, np.float32)
    opening = gripper_opening(state[:, 6:7], state[:, 7:8]).astype(np.float32)
    return np.concatenate([state[:, :6], opening], axis=1)


def import_lerobot(root: str | os.PathLike, repo_id: str, *, key_map: dict[str, str] | None = None,
                   cameras: list[str] | None = None, suite: str = "",
                   state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
                   image_fn: Callable[[str, np.ndarray], np.ndarray] | None = None,
                   episodes: list[int] | None = None, assume_success: bool = True) -> Iterator[Episode]:
    """Read a local LeRobotDataset (ours or a LIBERO demo conversion) as Episodes, source="import".

    key_map maps our names to the dataset's keys: "state", "action", "success", "joint_pos" and
    "images.<cam>" (defaults: observation.state, action, success if present, none, and every
    observation.images.<cam>). `cameras` picks and orders cameras (our names). `state_fn` turns the
    (N, D) state column into (N, 7) proprio; by default 7-D is kept and 8-D LIBERO states go
    through `libero_state8_to_proprio`. `image_fn(cam, frames)` can fix orientation (frames are
    (N, H, W, 3) uint8; ours must be upright). Without a success column, the last frame's success
    is `assume_success` (demonstrations succeed) and earlier frames are False.
    """
    root = Path(root)
    ds = _lerobot_dataset()(repo_id, root=root, return_uint8=True, video_backend=video_backend())
    feats = ds.features
    km = {"state": STATE_KEY, "action": ACTION_KEY}
    if SUCCESS_KEY in feats:
        km["success"] = SUCCESS_KEY
    for k, ft in feats.items():
        if k.startswith(IMAGE_PREFIX) and ft["dtype"] in ("image", "video"):
            km["images." + k[len(IMAGE_PREFIX):]] = k
    km.update(key_map or {})
    all_cams = [k[len("images."):] for k in km if k.startswith("images.")]
    cams = all_cams if cameras is None else list(cameras)
    for name in ["state", "action", *("images." + c for c in cams)]:
        if name not in km or km[name] not in feats:
            raise KeyError(f"{root}: no dataset key for {name!r} (mapped to {km.get(name)!r}); "
                           f"dataset has {sorted(feats)}; pass key_map={{{name!r}: '<key>'}}")
    video_cams = [c for c in cams if feats[km["images." + c]]["dtype"] == "video"]

    side_meta = {}
    side = root / EPISODE_META_FILE
    if side.exists():
        for line in side.read_text().splitlines():
            d = json.loads(line)
            side_meta[int(d.pop("episode_index"))] = d

    task_of = {int(v): k for k, v in ds.meta.tasks["task_index"].items()}
    ep_rows = ds.meta.episodes
    hf = ds.hf_dataset.with_format("numpy")
    columns = [km[n] for n in ["state", "action", "success", "joint_pos"] if n in km]
    columns += [km["images." + c] for c in cams if c not in video_cams]
    has_pad = PAD_KEY in feats
    if has_pad:
        columns.append(PAD_KEY)
    wanted = range(ds.meta.total_episodes) if episodes is None else episodes
    table = hf.select_columns(columns + ["episode_index", "frame_index", "task_index"])

    for e in wanted:
        row = ep_rows[int(e)]
        lo, hi = int(row["dataset_from_index"]), int(row["dataset_to_index"])
        block = table[lo:hi]
        if not (block["episode_index"] == e).all() or not (np.diff(block["frame_index"]) == 1).all():
            raise ValueError(f"{root}: rows {lo}:{hi} are not episode {e} in frame order")
        n = hi - lo
        # Our exports pad the terminal frame's action; foreign datasets have one action per frame
        # and lose the last one (see module docstring).
        T = n - 1
        if has_pad and not bool(np.asarray(block[PAD_KEY]).reshape(n)[-1]):
            log.warning("%s episode %d: last action is not padding; dropping it", root, e)
        # Video frames only come decoded through the dataset's item access (one call gives every
        # camera of a frame); image columns come straight from the arrow table.
        decoded = {c: [] for c in video_cams}
        for i in range(lo, hi) if video_cams else ():
            item = ds[i]
            for c in video_cams:
                decoded[c].append(item[km["images." + c]].numpy().transpose(1, 2, 0))
        images = {}
        for c in cams:
            frames = np.stack(decoded[c]) if c in video_cams else np.asarray(block[km["images." + c]])
            if frames.dtype != np.uint8:
                frames = _to_uint8(frames)
            images[c] = image_fn(c, frames) if image_fn else frames
        state = np.asarray(block[km["state"]], np.float32).reshape(n, -1)
        if state_fn is not None:
            proprio = state_fn(state)
        elif state.shape[1] == PROPRIO_DIM:
            proprio = state
        elif state.shape[1] == 8:
            proprio = libero_state8_to_proprio(state)
        else:
            raise ValueError(f"{root}: state is {state.shape[1]}-D; pass state_fn to map it to 7-D proprio")
        if "success" in km:
            success = np.asarray(block[km["success"]]).reshape(n).astype(bool)
        else:
            success = np.zeros(n, bool)
            success[-1] = assume_success
        joint = (np.asarray(block[km["joint_pos"]], np.float64).reshape(n, JOINT_DIM) if "joint_pos" in km
                 else np.full((n, JOINT_DIM), np.nan))
        actions = np.asarray(block[km["action"]], np.float32).reshape(n, -1)[:T]

        instruction = task_of[int(block["task_index"][0])]
        if int(e) in side_meta:
            d = dict(side_meta[int(e)])
            d["extra"] = {**d.get("extra", {}), "original_source": d["source"]}
            d.update(source="import", cameras=cams)
            meta = EpisodeMeta(**d)
        else:
            meta = EpisodeMeta(
                suite=suite, task_id=int(block["task_index"][0]), task_name=instruction,
                instruction=instruction, init_state_index=-1, seed=-1, source="import",
                success=bool(success[-1]), fps=float(ds.meta.fps), cameras=cams,
                extra={"lerobot_repo_id": repo_id, "lerobot_episode_index": str(e)},
            )
        yield Episode(meta=meta, images=images, proprio=proprio, joint_pos=joint,
                      sim_state=np.zeros((n, 0)), success=success, actions=actions, step_extras={})


def _to_uint8(frames: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] (some readers return those) back to uint8 HWC."""
    if frames.ndim == 4 and frames.shape[1] == 3 and frames.shape[-1] != 3:
        frames = frames.transpose(0, 2, 3, 1)
    return np.clip(np.round(np.asarray(frames, np.float64) * 255.0), 0, 255).astype(np.uint8)
