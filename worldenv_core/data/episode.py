"""The in-memory episode: what every collector produces and every dataset consumes.

An episode of T steps holds T+1 frames and T actions. The extra frame is the state reached by
the last action (for a successful expert demo, the frame where the success oracle first fires);
dropping it would lose exactly the frame the reflector most needs to see labelled positive.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from worldenv_core.robot import ACTION_DIM, JOINT_DIM, PROPRIO_DIM  # noqa: F401 (re-exported)
SOURCES = ("expert", "policy", "import", "imagined")  # imagined: a world-model rollout (not training data)


@dataclass
class EpisodeMeta:
    suite: str
    task_id: int
    task_name: str
    instruction: str
    init_state_index: int  # index into the benchmark's fixed init states, -1 when sampled from `seed`
    seed: int
    source: str  # "expert" | "policy" | "import"
    success: bool  # the oracle fired at some frame (per-frame flags in Episode.success)
    attempts: int = 1
    fps: float = 20.0
    cameras: list[str] = field(default_factory=list)
    extra: dict[str, str] = field(default_factory=dict)  # free-form string metadata

    def __post_init__(self) -> None:
        # Producers often hand over numpy scalars (np.int64 seeds, np.bool_ success); normalise to
        # Python types so metadata serialises the same way whatever the producer.
        self.task_id, self.init_state_index = int(self.task_id), int(self.init_state_index)
        self.seed, self.attempts, self.fps = int(self.seed), int(self.attempts), float(self.fps)
        self.success = bool(self.success)
        self.cameras = [str(c) for c in self.cameras]
        self.extra = dict(self.extra)
        if self.source not in SOURCES:
            raise ValueError(f"EpisodeMeta.source must be one of {SOURCES}, got {self.source!r}")
        if not self.fps > 0:
            raise ValueError(f"EpisodeMeta.fps must be positive, got {self.fps}")
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"EpisodeMeta.cameras has duplicates: {self.cameras}")
        for k, v in self.extra.items():
            if not isinstance(k, str) or not isinstance(v, str):
                raise ValueError(
                    f"EpisodeMeta.extra must map str -> str (it is stored as MCAP metadata); "
                    f"got {k!r}: {type(v).__name__}"
                )


def _as(name: str, value, dtype) -> np.ndarray:
    """Cast to the schema dtype. Images are excluded: casting float images to uint8 would
    silently destroy them, so they are checked instead (see Episode.__post_init__)."""
    try:
        return np.ascontiguousarray(np.asarray(value, dtype=dtype))
    except (TypeError, ValueError) as e:
        raise ValueError(f"Episode.{name}: cannot convert to {np.dtype(dtype).name}: {e}") from e


@dataclass
class Episode:
    steps_per_frame: ClassVar[int] = 1  # a frame every simulator step (a paired rollout's: every chunk)
    meta: EpisodeMeta
    images: dict[str, np.ndarray]  # camera -> uint8 (T+1, H, W, 3), upright
    proprio: np.ndarray  # (T+1, 7) float32
    joint_pos: np.ndarray  # (T+1, 7) float64
    sim_state: np.ndarray  # (T+1, S) float64, MuJoCo flattened state (S may be 0: unknown)
    success: np.ndarray  # (T+1,) bool: oracle success at that frame
    actions: np.ndarray  # (T, 7) float32: action taken at frame t
    step_extras: dict[str, np.ndarray] = field(default_factory=dict)  # (T, ...) float32

    def __post_init__(self) -> None:
        # Numeric arrays are cast to the schema dtypes so every producer writes the same file
        # layout; shapes are checked, never reshaped, so a wrong producer fails here, loudly.
        self.actions = _as("actions", self.actions, np.float32)
        if self.actions.ndim != 2 or self.actions.shape[1] != ACTION_DIM:
            raise ValueError(f"Episode.actions must be (T, {ACTION_DIM}), got {self.actions.shape}")
        T = self.actions.shape[0]
        n = T + 1

        def frames(name: str, value, dtype, tail: tuple[int, ...] | None) -> np.ndarray:
            arr = _as(name, value, dtype)
            if arr.ndim < 1 or arr.shape[0] != n:
                raise ValueError(
                    f"Episode.{name} must have T+1={n} frames (actions has T={T}), got shape {arr.shape}"
                )
            if tail is not None and arr.shape[1:] != tail:
                raise ValueError(f"Episode.{name} must be ({n}, {', '.join(map(str, tail))}), got {arr.shape}")
            return arr

        self.proprio = frames("proprio", self.proprio, np.float32, (PROPRIO_DIM,))
        self.joint_pos = frames("joint_pos", self.joint_pos, np.float64, (JOINT_DIM,))
        self.sim_state = frames("sim_state", self.sim_state, np.float64, None)
        if self.sim_state.ndim != 2:
            raise ValueError(f"Episode.sim_state must be ({n}, S), got {self.sim_state.shape}")
        success = np.asarray(self.success)
        if success.dtype != np.bool_:
            raise ValueError(f"Episode.success must be bool, got {success.dtype}")
        self.success = frames("success", success, np.bool_, ())

        for cam, img in self.images.items():
            img = np.asarray(img)
            if img.dtype != np.uint8:
                raise ValueError(f"Episode.images[{cam!r}] must be uint8, got {img.dtype}")
            if img.ndim != 4 or img.shape[0] != n or img.shape[3] != 3:
                raise ValueError(f"Episode.images[{cam!r}] must be ({n}, H, W, 3) uint8, got {img.shape}")
            self.images[cam] = np.ascontiguousarray(img)
        if list(self.images) != list(self.meta.cameras):
            raise ValueError(
                f"Episode.images cameras {list(self.images)} do not match meta.cameras {self.meta.cameras} "
                "(same names, same order)"
            )

        for key, val in list(self.step_extras.items()):
            if not key or "/" in key:
                raise ValueError(f"Episode.step_extras key {key!r} must be a non-empty name without '/'")
            arr = _as(f"step_extras[{key!r}]", val, np.float32)
            if arr.ndim < 1 or arr.shape[0] != T:
                raise ValueError(f"Episode.step_extras[{key!r}] must have T={T} rows, got shape {arr.shape}")
            self.step_extras[key] = arr

    @property
    def length(self) -> int:
        """T: the number of actions (the episode has T+1 frames)."""
        return int(self.actions.shape[0])

    @property
    def num_frames(self) -> int:
        return self.length + 1

    def video(self, camera: str):
        """One camera's frames as a torch uint8 tensor (T+1, 3, H, W), what the models read."""
        import torch  # (lazily: the episode format itself needs numpy only)

        return torch.from_numpy(self.images[camera]).permute(0, 3, 1, 2)

    def copy(self) -> "Episode":
        return copy.deepcopy(self)

    def equals(self, other: "Episode") -> bool:
        """Bit-exact equality of every field (NaNs compare equal to NaNs)."""
        return not episode_differences(self, other)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    # Compare raw bytes: catches -0.0 vs 0.0 and keeps NaN == NaN, which is what "bit-exact" means.
    return a.tobytes() == b.tobytes()


def episode_differences(a: Episode, b: Episode) -> list[str]:
    """Names of the fields where a and b differ (empty when bit-identical). Used by tests and by
    tools that check a round trip; the names make a failing comparison readable."""
    diffs = []
    if a.meta != b.meta:
        diffs.append("meta")
    for name in ("proprio", "joint_pos", "sim_state", "success", "actions"):
        if not _same(getattr(a, name), getattr(b, name)):
            diffs.append(name)
    if list(a.images) != list(b.images):
        diffs.append("images.keys")
    else:
        diffs += [f"images[{c}]" for c in a.images if not _same(a.images[c], b.images[c])]
    if set(a.step_extras) != set(b.step_extras):
        diffs.append("step_extras.keys")
    else:
        diffs += [f"step_extras[{k}]" for k in a.step_extras if not _same(a.step_extras[k], b.step_extras[k])]
    return diffs
