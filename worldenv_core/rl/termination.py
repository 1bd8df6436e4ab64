"""Dynamic termination by the reflector: a rollout stops at the first check where R > eta.

Labels: y_t = 1 from the step the oracle first reports success onward (the task, once done,
counts as done: the reflector answers "has g been completed by frame t").

Termination is judged per episode against the oracle's first success step t_s:
* correct stop: the reflector stops at t_stop >= t_s (timing error t_stop - t_s);
* false stop: it stops before success, or in an episode that never succeeds;
* missed success: the episode succeeds and the reflector never stops.
Termination precision/recall/F1 count a correct stop as a true positive, a false stop as a
false positive and a missed success as a false negative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


def success_labels(success: np.ndarray) -> np.ndarray:
    """Per-frame oracle flags -> y_t: 1 from the first success onward."""
    return np.maximum.accumulate(np.asarray(success, dtype=bool))


def first_success(success: np.ndarray) -> int | None:
    hits = np.flatnonzero(np.asarray(success, dtype=bool))
    return int(hits[0]) if len(hits) else None


def check_steps(num_frames: int, every: int) -> list[int]:
    """The frames a chunked rollout is scored at: the first, every `every`-th, and the last."""
    steps = list(range(0, num_frames, every))
    if steps[-1] != num_frames - 1:
        steps.append(num_frames - 1)
    return steps


@dataclass
class StopOutcome:
    t_success: int | None
    t_stop: int | None

    @property
    def kind(self) -> str:
        if self.t_stop is None:
            return "missed" if self.t_success is not None else "no_stop"
        if self.t_success is not None and self.t_stop >= self.t_success:
            return "correct"
        return "false_stop"


def first_stop(steps, scores, eta: float) -> int | None:
    """The first checked step whose score exceeds eta, or None."""
    above = np.flatnonzero(np.asarray(scores, dtype=float) > eta)
    return int(steps[above[0]]) if len(above) else None


def episode_outcomes(flags, check_steps_: list[int], scores, eta: float) -> dict[str, dict]:
    """One rollout run to its horizon, judged under every termination mode at once.

    flags: the oracle's per-frame success flags of the whole rollout; check_steps_/scores: the
    steps where the reflector was asked and its R there. With a deterministic policy and
    simulator, the rollout an `oracle` or `reflector` episode would have run is this one cut
    short, so each mode's outcome is read off it: `oracle` ends at the first success, `fixed`
    at the horizon, `reflector` at the first check with R > eta (else the horizon); success is
    the oracle's flag at that frame. Returns mode -> {success, steps, stop_step}."""
    flags = np.asarray(flags, dtype=bool)
    last = len(flags) - 1
    t_success = first_success(flags)
    t_stop = first_stop(check_steps_, scores, eta) if len(scores) else None
    oracle_end = last if t_success is None else t_success
    reflector_end = last if t_stop is None else t_stop
    return {"oracle": {"success": bool(flags[oracle_end]), "steps": oracle_end, "stop_step": None},
            "fixed": {"success": bool(flags[last]), "steps": last, "stop_step": None},
            "reflector": {"success": bool(flags[reflector_end]), "steps": reflector_end, "stop_step": t_stop}}


def best_eta(f1_by_eta: dict, prior: float) -> float:
    """The threshold with the highest termination F1 (NaN counts as worst); ties go to the one
    closest to `prior` (the configured eta), so a flat sweep keeps it."""
    def key(item):
        eta, f1 = float(item[0]), float(item[1])
        return (-np.inf if np.isnan(f1) else f1, -abs(eta - prior))
    return float(max(f1_by_eta.items(), key=key)[0])


def termination_metrics(outcomes: list[StopOutcome]) -> dict:
    kinds = [o.kind for o in outcomes]
    tp, fp, fn = kinds.count("correct"), kinds.count("false_stop"), kinds.count("missed")
    n_success = sum(o.t_success is not None for o in outcomes)
    early = [o for o in outcomes if o.kind == "false_stop" and o.t_success is not None]
    timing = [o.t_stop - o.t_success for o in outcomes if o.kind == "correct"]
    return {
        "episodes": len(outcomes), "successful_episodes": n_success,
        "correct_stops": tp, "false_stops": fp, "false_stops_before_success": len(early), "missed_successes": fn,
        "no_stop_failures": kinds.count("no_stop"),
        "precision": tp / (tp + fp) if tp + fp else float("nan"),
        "recall": tp / (tp + fn) if tp + fn else float("nan"),
        "f1": 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else float("nan"),
        # rates over the episodes where the event is possible
        "false_stop_before_success_rate": len(early) / n_success if n_success else float("nan"),
        "false_stop_in_failure_rate": (fp - len(early)) / (len(outcomes) - n_success) if len(outcomes) > n_success else float("nan"),
        "missed_success_rate": fn / n_success if n_success else float("nan"),
        "timing_error_mean": float(np.mean(timing)) if timing else float("nan"),
        "timing_error_median": float(np.median(timing)) if timing else float("nan"),
        "early_stop_error_mean": float(np.mean([o.t_success - o.t_stop for o in early])) if early else float("nan"),
    }


def check_eta(eta: float) -> float:
    """The reward threshold must be a probability."""
    if isinstance(eta, bool) or not isinstance(eta, (int, float)) or not 0.0 <= float(eta) <= 1.0:
        raise ValueError(f"eta (the reflector's success threshold) must be in [0, 1], got {eta!r}")
    return float(eta)


def reflector_eta(path, eta: float | None) -> float:
    """The threshold a stage stops at: `eta` when given, else the one the reflector checkpoint
    carries (its train_reflector eta, or the one its eta cross-validation chose)."""
    from worldenv_core.models.checkpoint import read_config

    return check_eta(read_config(path)["meta"].get("eta", 0.5) if eta is None else eta)


class ReflectorStop:
    """Dynamic termination for one real-simulator episode: called with the boundary images of
    every chunk, it adds the reflector camera's frame to an incremental scorer and answers
    whether R > eta. `scores` keeps R at every check. watch=True only records (never stops): one
    rollout to the horizon then serves every termination mode (`episode_outcomes`)."""

    def __init__(self, model, eta: float, instruction: str, encoder, watch: bool = False):
        self.scorer = model.scorer([instruction], encoder)
        self.eta, self.cameras, self.scores, self.watch = check_eta(eta), [model.camera], [], watch

    def __call__(self, images: dict) -> bool:
        frame = torch.from_numpy(images[self.cameras[0]]).permute(2, 0, 1)[None]
        self.scorer.add(frame)
        self.scores.append(float(self.scorer.score()[0]))
        return not self.watch and self.scores[-1] > self.eta
