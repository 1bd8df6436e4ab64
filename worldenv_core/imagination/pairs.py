"""Paired rollouts on disk, and as a reflector's training data.

`evaluate_imagination` keeps both sides of every paired rollout at every check (the imagined
frames and the real simulator's frames of the same actions, one `.npz` a pair, beside the
policy variant's rows). The same pairs, made on the world model's *training* episodes
(`contexts.source=training`), are verdict fidelity's first lever: imagined video labelled
with the real outcome of the same actions, the policy's own near misses and failures included,
and real frames of those actions beside them. `checked_episodes` turns them into episodes the
reflector's prefix sampler reads: frame k is the check after k chunks, and its label is whether
the real simulator had succeeded by then (the question the verdict asks at that check).
"""

from __future__ import annotations

import functools
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


def pair_past(row: dict, camera: str, every: int):
    """The recorded frames before a pair's mid-episode context that its reward model was shown on both sides
    (`Context.history`), (n, 3, H, W) uint8; None for an init-state context. Read once per start: a context's
    rollouts are several rows (shared, not to be written to)."""
    if row.get("context_kind") != "episode":
        return None
    return _start_past(str(row["start"]), int(row["task_id"]), camera, every)


@functools.lru_cache(maxsize=64)
def _start_past(start: str, task_id: int, camera: str, every: int):
    from worldenv_core.envs.replay import RealStart, recorded_history  # the simulator's side: only when asked

    episode, frame = start.rsplit("@", 1)
    return recorded_history(RealStart(task_id=task_id, episode=episode, frame=int(frame)), camera, every)


def start_episode(row: dict) -> str | None:
    """The collected episode a pair's context is a frame of (None: a benchmark init state)."""
    return episode_key(str(row["start"]).rsplit("@", 1)[0]) if row.get("context_kind") == "episode" else None


def calibration_starts(folders: list[Path], every: int) -> set[str]:
    """The episodes whose pairs choose eta instead of training (`train.pairs_eta_every`): every
    `every`-th distinct start episode of the pairs, in key order, so the set mixes tasks like the
    whole; 0 = none."""
    if not every:
        return set()
    starts = sorted({s for folder in folders for row, _ in paired_rows(folder) if (s := start_episode(row))})
    return set(starts[every - 1::every])


def checked_episodes(folder: Path, instructions: dict[int, str], forbidden: set[str],
                     set_aside: set[str] = frozenset(), past_of=lambda row: None) -> list[CheckedEpisode]:
    """Both sides of every pair in `folder` with its real labels. Refused when a pair starts at a
    benchmark init state (the evaluations') or in one of `forbidden` (the reflector's held-out
    episodes): training there would score the test. Pairs whose real replay failed are skipped,
    and so are those starting in `set_aside` (kept to choose eta: `calibration_rows`). `past_of(row)`
    (`pair_past`): the recorded frames before the pair's keyframe, put before both sides as checks
    not yet succeeded, so the reflector trains on the whole prefixes it is asked about."""
    out = []
    for row, path in paired_rows(folder):
        start = start_episode(row)
        if start is None or start in forbidden:
            raise ValueError(f"{folder}: pair {path.name} starts {'at a benchmark init state' if start is None else 'in '
                             + start}, which evaluations judge on; make the pairs with contexts.source=training")
        if row.get("real_error") or start in set_aside:
            continue
        task = int(row["task_id"])
        if task not in instructions:
            raise ValueError(f"{folder}: pair {path.name} is of task {task}, which none of the training episodes is")
        chunk, first = int(row["chunk"]), row["real_first_success"]
        with np.load(path) as f:
            sides = {side: f[side] for side in SIDES}
        past = past_of(row)
        past = np.zeros((0, *sides["real"].shape[1:]), np.uint8) if past is None else past.permute(0, 2, 3, 1).numpy()
        for side, frames in sides.items():
            checks = np.arange(len(frames)) * chunk
            success = checks >= first if first is not None else np.zeros(len(frames), dtype=bool)
            frames, success = np.concatenate([past, frames]), np.concatenate([np.zeros(len(past), bool), success])
            meta = SimpleNamespace(task_id=task, instruction=instructions[task], side=side, start=row["start"])
            out.append(CheckedEpisode(frames, success, meta, chunk))
    return out


def calibration_rows(folders: list[Path], starts: set[str]) -> list[tuple[dict, Path]]:
    """The stored pairs that start in `starts` (`calibration_starts`), real replay intact."""
    return [(row, path) for folder in folders for row, path in paired_rows(folder)
            if start_episode(row) in starts and not row.get("real_error")]


def eta_on_pairs(rows: list[tuple[dict, Path]], score, grid, prior: float) -> dict:
    """eta chosen on paired rollouts the reflector did not train on, by the verdict's own F1 (the
    imagined stop against the real outcome of the same actions, `verdict_metrics`): the
    threshold the verdict is used at, chosen on imagined video, not on real frames.
    `score(row, imagined_frames) -> R after every check`."""
    from worldenv_core.imagination.verdict import verdict_metrics
    from worldenv_core.rl.termination import best_eta

    rescored = []
    for i, (row, path) in enumerate(rows):
        with np.load(path) as f:
            rescored.append({**row, "context": i, "imagined_scores": score(row, f["imagined"])})
    sweep = {e: verdict_metrics(rescored, e) for e in grid}
    chosen = best_eta({e: m["f1"] for e, m in sweep.items()}, prior)
    return {"pairs": len(rows), "chosen_eta": chosen,
            "eta_sweep": {str(e): {k: m[k] for k in ("f1", "precision", "recall", "hack_rate", "imagined_success",
                                                      "real_success")} for e, m in sweep.items()},
            "at_chosen": {k: sweep[chosen][k] for k in ("f1", "precision", "recall", "hack_rate", "auroc")}}
