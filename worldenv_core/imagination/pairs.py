"""Paired rollouts on disk, and as a reflector's training data.

`evaluate_imagination` keeps both sides of every paired rollout at every check (the imagined
frames and the real simulator's frames of the same actions, one `.npz` a pair, beside the
policy variant's rows). The same pairs, made on the world model's *training* episodes
(`contexts.source=training`), are what issue 22's first lever asks for: imagined video labelled
with the real outcome of the same actions, the policy's own near misses and failures included,
and real frames of those actions beside them. `checked_episodes` turns them into episodes the
reflector's prefix sampler reads: frame k is the check after k chunks, and its label is whether
the real simulator had succeeded by then (the question the verdict asks at that check).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from worldenv_core.data.selection import episode_key

SIDES = ("imagined", "real")


def store_pair_frames(path: Path, imagined: dict[int, np.ndarray], real: dict[int, np.ndarray]) -> None:
    """One pair's frames at every check, step order (H, W, 3 uint8 each), written whole or not at all."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, imagined=np.stack([imagined[s] for s in sorted(imagined)]),
                        real=np.stack([real[s] for s in sorted(real)]))
    tmp.replace(path)


@dataclass
class CheckedEpisode:
    """One side of a paired rollout as a reflector training episode: its frames at the checks
    (every `steps_per_frame` simulator steps, the first the context frame) and, per check, whether
    the real simulator had succeeded by then with the same actions."""

    frames: np.ndarray  # (K, H, W, 3) uint8
    success: np.ndarray  # (K,) bool
    meta: SimpleNamespace  # task_id, instruction, side, start: what the sampler and a reader need
    steps_per_frame: int

    def video(self, camera: str | None = None):
        import torch

        return torch.from_numpy(self.frames).permute(0, 3, 1, 2)


def paired_rows(folder: Path) -> list[tuple[dict, Path]]:
    """Every stored pair of an `evaluate_imagination` work dir: (row, its frames file), over the
    policy variants whose frames were kept."""
    out = []
    for variant in sorted(Path(folder).glob("*.json")):
        frames = variant.parent / "frames" / variant.stem
        if not frames.is_dir():  # fidelity.json, pairs.json, and variants run without store_frames
            continue
        rows = json.loads(variant.read_text())["rows"]
        out += [(row, frames / f"{i:04d}.npz") for i, row in enumerate(rows)]
    if not out:
        raise FileNotFoundError(f"{folder} holds no stored pairs (a work dir of evaluate_imagination run with "
                                "store_frames=true)")
    return out


def start_episode(row: dict) -> str | None:
    """The collected episode a pair's context is a frame of (None: a benchmark init state)."""
    return episode_key(str(row["start"]).rsplit("@", 1)[0]) if row.get("context_kind") == "episode" else None


def checked_episodes(folder: Path, instructions: dict[int, str], forbidden: set[str]) -> list[CheckedEpisode]:
    """Both sides of every pair in `folder` with its real labels. Refused when a pair starts at a
    benchmark init state (the evaluations') or in one of `forbidden` (the reflector's held-out
    episodes): training there would score the test. Pairs whose real replay failed are skipped."""
    out = []
    for row, path in paired_rows(folder):
        start = start_episode(row)
        if start is None or start in forbidden:
            raise ValueError(f"{folder}: pair {path.name} starts {'at a benchmark init state' if start is None else 'in '
                             + start}, which evaluations judge on; make the pairs with contexts.source=training")
        if row.get("real_error"):
            continue
        task = int(row["task_id"])
        if task not in instructions:
            raise ValueError(f"{folder}: pair {path.name} is of task {task}, which none of the training episodes is")
        chunk, first = int(row["chunk"]), row["real_first_success"]
        with np.load(path) as f:
            sides = {side: f[side] for side in SIDES}
        for side, frames in sides.items():
            checks = np.arange(len(frames)) * chunk
            success = checks >= first if first is not None else np.zeros(len(frames), dtype=bool)
            meta = SimpleNamespace(task_id=task, instruction=instructions[task], side=side, start=row["start"])
            out.append(CheckedEpisode(frames, success, meta, chunk))
    return out
