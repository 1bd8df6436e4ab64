"""Torch dataset over MCAP episode files, in three sampling modes.

  frame    one frame: the observation at t and the action taken there (policy SFT, reflector)
  chunk    the observation at t, the next `chunk` actions and the next `chunk` frames, plus
           optionally `history` past frames (action-chunk policies, world-model training)
  episode  a whole episode (reflector over o_{1:t}, evaluation, RL contexts)

Windows that run past the end of an episode are padded and masked (`*_is_pad`, True = padding),
never dropped, so the last steps of every episode, where success fires, are still sampled.

Decoded episodes are cached in memory on first use (datasets here are small: ~30 MB per
300-frame episode at 2x128 px). With DataLoader workers each worker keeps its own cache.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from .episode import Episode
from .mcap_io import CorruptEpisodeError, EpisodeInfo, list_episode_files, read_episode, read_info

log = logging.getLogger(__name__)

MODES = ("frame", "chunk", "episode")
STAT_KEYS = ("proprio", "action")


class _Cached:
    """An episode converted once into the tensors items are sliced from (images CHW)."""

    def __init__(self, ep: Episode, extras: Iterable[str]):
        self.episode = ep
        self.T = ep.length
        self.images = {c: torch.from_numpy(np.ascontiguousarray(v.transpose(0, 3, 1, 2))) for c, v in ep.images.items()}
        self.proprio = torch.from_numpy(ep.proprio)
        self.actions = torch.from_numpy(ep.actions)
        self.success = torch.from_numpy(ep.success)
        self.extras = {k: torch.from_numpy(ep.step_extras[k]) for k in extras}


class EpisodeDataset(Dataset):
    """Samples from MCAP episodes (see module docstring for the modes and item keys).

    Args:
      paths: a directory (searched recursively for *.mcap) or an iterable of files.
      cameras: cameras to load (None: those of the first episode); all episodes must have them
        with the same image size.
      mode: "frame" | "chunk" | "episode".
      chunk: actions / future frames per item in chunk mode.
      history: past frames per item in chunk mode (padded before t=0 with frame 0).
      include_terminal: frame mode also yields the final frame T (no action: padded, masked).
      pad: "edge" repeats the last valid action/frame into the padding, "zeros" fills zeros.
      step_extras: per-step arrays (e.g. ["mu", "beta"]) to include; every episode must have them.
      load_sim_state: also decode sim_state (only returned in episode mode).
      on_error: "skip" drops files whose metadata cannot be read (warning), "raise" raises.
      cache: keep decoded episodes in memory.
      transform: applied to each item dict before it is returned.
      future_frames: chunk mode also returns the K frames the actions lead to (world models need
        them, policies do not).
    """

    def __init__(self, paths: str | Path | Iterable[str | Path], cameras: list[str] | None = None,
                 mode: str = "frame", chunk: int = 8, *, history: int = 0, include_terminal: bool = False,
                 pad: str = "edge", step_extras: Iterable[str] = (), load_sim_state: bool = False,
                 on_error: str = "skip", cache: bool = True, transform: Callable[[dict], dict] | None = None,
                 future_frames: bool = True):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if chunk < 1 or history < 0:
            raise ValueError(f"need chunk >= 1 and history >= 0, got chunk={chunk}, history={history}")
        if pad not in ("edge", "zeros"):
            raise ValueError(f"pad must be 'edge' or 'zeros', got {pad!r}")
        if on_error not in ("skip", "raise"):
            raise ValueError(f"on_error must be 'skip' or 'raise', got {on_error!r}")
        self.mode, self.chunk, self.history = mode, chunk, history
        self.include_terminal, self.pad = include_terminal, pad
        self.step_extras = list(step_extras)
        self.load_sim_state, self.use_cache, self.transform = load_sim_state, cache, transform
        self.future_frames = future_frames  # chunk mode: policies need only the actions ahead

        self.infos: list[EpisodeInfo] = []
        for p in list_episode_files(paths):
            try:
                self.infos.append(read_info(p))
            except CorruptEpisodeError as e:
                if on_error == "raise":
                    raise
                log.warning("skipping %s", e)
        if not self.infos:
            raise ValueError(f"no readable episode files in {paths!r}")
        self.cameras = list(self.infos[0].meta.cameras) if cameras is None else list(cameras)
        self._check_consistent()

        # Flat index of (episode, frame) pairs; built from metadata alone, so constructing the
        # dataset costs one small read per file, not a decode.
        if mode == "episode":
            ep_idx = np.arange(len(self.infos))
            t_idx = np.zeros(len(self.infos), np.int64)
        else:
            extra = 1 if (mode == "frame" and include_terminal) else 0
            counts = [info.length + extra for info in self.infos]
            ep_idx = np.repeat(np.arange(len(self.infos)), counts)
            t_idx = np.concatenate([np.arange(c) for c in counts]) if counts else np.zeros(0, np.int64)
        self._ep_idx, self._t_idx = ep_idx.astype(np.int64), t_idx.astype(np.int64)
        self._cache: dict[int, _Cached] = {}
        self._stats: dict | None = None

    def _check_consistent(self) -> None:
        ref_shapes = None
        for info in self.infos:
            missing = [c for c in self.cameras if c not in info.meta.cameras]
            if missing:
                raise ValueError(f"{info.path}: cameras {missing} missing (it has {info.meta.cameras})")
            shapes = {c: info.image_shapes[c] for c in self.cameras}
            if ref_shapes is None:
                ref_shapes, ref_path = shapes, info.path
            elif shapes != ref_shapes:
                raise ValueError(f"{info.path}: image shapes {shapes} differ from {ref_path}: {ref_shapes}")
            lost = [k for k in self.step_extras if k not in info.step_extras]
            if lost:
                raise ValueError(f"{info.path}: step_extras {lost} missing (it has {list(info.step_extras)})")
        self.image_shapes = ref_shapes

    # ------------------------------------------------------------------ episodes

    @property
    def num_episodes(self) -> int:
        return len(self.infos)

    @property
    def paths(self) -> list[Path]:
        return [info.path for info in self.infos]

    def _get(self, i: int) -> _Cached:
        c = self._cache.get(i)
        if c is None:
            ep = read_episode(self.infos[i].path, cameras=self.cameras, load_sim_state=self.load_sim_state)
            c = _Cached(ep, self.step_extras)
            if self.use_cache:
                self._cache[i] = c
        return c

    def get_episode(self, i: int) -> Episode:
        """The i-th episode as loaded (requested cameras only)."""
        return self._get(i).episode

    # ------------------------------------------------------------------ items

    def __len__(self) -> int:
        return len(self._ep_idx)

    def __getitem__(self, idx: int) -> dict:
        if idx < 0:
            idx += len(self)
        if not 0 <= idx < len(self):
            raise IndexError(f"index {idx} out of range for {len(self)} items")
        e, t = int(self._ep_idx[idx]), int(self._t_idx[idx])
        c = self._get(e)
        meta = c.episode.meta
        item = {"instruction": meta.instruction, "task_id": meta.task_id, "episode_index": e}
        if self.mode == "episode":
            item.update(self._episode_item(c))
        else:
            item["frame_index"] = t
            item["images"] = {cam: v[t] for cam, v in c.images.items()}
            item["proprio"] = c.proprio[t]
            item["success"] = c.success[t]
            if self.mode == "frame":
                item.update(self._frame_actions(c, t))
            else:
                item.update(self._chunk_item(c, t))
        return self.transform(item) if self.transform else item

    def _frame_actions(self, c: _Cached, t: int) -> dict:
        if t < c.T:
            return {"action": c.actions[t], "action_is_pad": torch.tensor(False),
                    "extras": {k: v[t] for k, v in c.extras.items()}}
        # the terminal frame has no action (include_terminal=True only)
        src = t - 1 if (self.pad == "edge" and c.T > 0) else None
        pick = lambda v: v[src].clone() if src is not None else torch.zeros(v.shape[1:], dtype=v.dtype)  # noqa: E731
        return {"action": pick(c.actions), "action_is_pad": torch.tensor(True),
                "extras": {k: pick(v) for k, v in c.extras.items()}}

    def _window(self, values: torch.Tensor, idx: np.ndarray, valid: np.ndarray) -> torch.Tensor:
        """values[idx] where valid; elsewhere the nearest valid entry ("edge") or zeros."""
        last = len(values) - 1
        out = values[torch.from_numpy(np.clip(idx, 0, max(last, 0)))]
        if self.pad == "zeros" and not valid.all():
            out[torch.from_numpy(~valid)] = 0
        return out

    def _chunk_item(self, c: _Cached, t: int) -> dict:
        K = self.chunk
        a_idx = t + np.arange(K)  # actions t .. t+K-1
        a_ok = a_idx < c.T
        f_idx = t + 1 + np.arange(K)  # frames t+1 .. t+K (the frames those actions lead to)
        f_ok = f_idx <= c.T
        item = {
            "actions": self._window(c.actions, a_idx, a_ok),
            "action_is_pad": torch.from_numpy(~a_ok),
            "extras": {k: self._window(v, a_idx, a_ok) for k, v in c.extras.items()},
        }
        if self.future_frames:
            item.update({
                "future_images": {cam: self._window(v, f_idx, f_ok) for cam, v in c.images.items()},
                "future_proprio": self._window(c.proprio, f_idx, f_ok),
                "future_success": self._window(c.success, f_idx, f_ok),
                "future_is_pad": torch.from_numpy(~f_ok),
            })
        if self.history:
            h_idx = t - self.history + np.arange(self.history)  # frames t-h .. t-1
            h_ok = h_idx >= 0
            item["past_images"] = {cam: self._window(v, h_idx, h_ok) for cam, v in c.images.items()}
            item["past_proprio"] = self._window(c.proprio, h_idx, h_ok)
            item["past_is_pad"] = torch.from_numpy(~h_ok)
        return item

    def _episode_item(self, c: _Cached) -> dict:
        ep = c.episode
        item = {
            "length": c.T,
            "images": dict(c.images),
            "proprio": c.proprio,
            "joint_pos": torch.from_numpy(ep.joint_pos),
            "success": c.success,
            "actions": c.actions,
            "extras": dict(c.extras),
        }
        if self.load_sim_state:
            item["sim_state"] = torch.from_numpy(ep.sim_state)
        return item

    # ------------------------------------------------------------------ stats

    def compute_stats(self) -> dict[str, dict[str, np.ndarray]]:
        """Per-dimension mean/std/min/max (float32) of proprio (all T+1 frames of every episode)
        and action (all T actions), plus `count`. Reads only the /state and /action channels of
        episodes not already cached, so this stays cheap on large image datasets."""
        if self._stats is None:
            proprio, action = [], []
            for i, info in enumerate(self.infos):
                if i in self._cache:
                    ep = self._cache[i].episode
                else:
                    ep = read_episode(info.path, cameras=[], load_sim_state=False)
                for name, arr in (("proprio", ep.proprio), ("action", ep.actions)):
                    if not np.isfinite(arr).all():
                        # one NaN would silently turn every normalised input into NaN
                        raise ValueError(f"non-finite {name} values in {info.path}; cannot compute stats")
                proprio.append(ep.proprio)
                action.append(ep.actions)
            self._stats = {k: _stats(np.concatenate(v)) for k, v in zip(STAT_KEYS, (proprio, action))}
        return self._stats


def _stats(x: np.ndarray) -> dict[str, np.ndarray]:
    x = x.astype(np.float64)  # accumulate in float64: float32 sums drift over ~1e5 frames
    if len(x) == 0:
        nan = np.full(x.shape[1:], np.nan, np.float32)
        return {"mean": nan, "std": nan, "min": nan, "max": nan, "count": np.int64(0)}
    return {
        "mean": x.mean(0).astype(np.float32),
        "std": x.std(0).astype(np.float32),
        "min": x.min(0).astype(np.float32),
        "max": x.max(0).astype(np.float32),
        "count": np.int64(len(x)),
    }
