"""Further reflectors judging the same pairs (`more_reflectors`): the reflector ablation at no
rollout of its own.

The imagined rollouts do not depend on the reflector (they are watched to the horizon and the
policy sees only frames), so another reflector's verdict on a pair is its score of the same
imagined frames and the same real frames at the same checks. The paired run keeps both sides'
frames at every check in its work dir (`store_frames`); a reflector named now or in a later run
scores them there, and its scores join the pairs file, so naming it again costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worldenv_core.imagination.verdict import rescored


@dataclass(frozen=True)
class Judge:
    """A further reflector and the threshold it judges at (its own)."""

    name: str  # its record id (or checkpoint folder name)
    path: str
    eta: float


def judge_pairs(rows: list[dict], frames_dir: Path, judges: list[Judge], load, instruction_of, encoder,
                past_of=lambda row: None) -> bool:
    """Score every row's stored frames with each judge it has no scores of yet (`row["more_reflectors"]`).
    `load(judge) -> reward model`; `instruction_of(row) -> str`; `past_of(row)`: a mid-episode context's recorded
    frames before it, which every judge is shown as the terminating reflector was. -> whether anything was added."""
    todo = [j for j in judges if any(j.name not in r["more_reflectors"] for r in rows)]
    for j in todo:
        model = load(j)
        for i, row in enumerate(rows):
            if j.name in row["more_reflectors"]:
                continue
            path = frames_dir / f"{i:04d}.npz"
            if not path.exists():
                raise FileNotFoundError(f"{path} is missing: the pairs were made without store_frames, so "
                                        f"{j.name} cannot judge them; run again with store_frames=true")
            with np.load(path) as f:
                row["more_reflectors"][j.name] = {
                    side: rescored(model, instruction_of(row), f[key], encoder, past_of(row))
                    for side, key in (("imagined_scores", "imagined"), ("real_scores", "real"))}
    return bool(todo)
