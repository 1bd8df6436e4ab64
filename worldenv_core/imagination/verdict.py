"""Verdict fidelity: does the imagined environment judge a rollout as the real simulator would?

`imagine` runs a policy in the imagined environment exactly as LOOP does (`collect_rollouts`:
the same env, Laplace-sampled actions), watched to the horizon, and keeps per rollout the actions
it executed, the reflector's score after every chunk and the imagined frames at a few steps.
`envs.replay` executes those actions in the real simulator; `pair` joins both sides; `judge`
reads off the verdicts at any eta (imagination stops at the first check with R > eta, exactly as
in LOOP; the real outcome is the oracle firing by that step); the functions below measure the
agreement:

* `verdict_metrics`: AUROC of the imagined reward against the real outcome; precision, recall
  and F1 of imagined success at eta; the hack rate (imagined successes that fail in reality);
  the timing error; the same numbers for the reflector on the *real* frames of the same actions,
  asked at the imagined verdict's check and as a terminator of its own (`reflector_on_real`),
  which separates the world model's error from the reflector's;
* `frame_metrics`: PSNR / SSIM of imagined against real frames along the paired trajectories;
* `evaluator_metrics`: the world model as a policy evaluator (Spearman and MAE between imagined
  and real success over policies).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import torch

from worldenv_core.imagination.env import Context, ImaginedEnv, StepResult
from worldenv_core.stats import binary_metrics, cluster_bootstrap_ci, spearman
from worldenv_core.metrics import psnr, ssim


@dataclass
class ImaginedRun:
    """One imagined rollout, watched to the horizon: what the real simulator needs to replay it,
    and the reflector's score at every chunk boundary (the verdict at any eta is read off them)."""

    context: int
    actions: np.ndarray  # (steps, 7) float32, simulator units
    scores: list[float]  # R at steps 0, K, 2K, ... (the check after each chunk)
    steps: int  # the horizon, rounded up to a chunk
    frames: dict[int, np.ndarray] = field(default_factory=dict)  # step -> (H, W, 3) uint8, chunk boundaries


class _Keeper:
    """A `collect_rollouts` observer: per rollout, the actions it executed, the reflector's score
    after each chunk, and its imagined frames at the steps in `keep` (every chunk boundary for
    rollouts in `full`)."""

    def __init__(self, keep: set[int], full: set[int]):
        self.keep, self.full = keep, full
        self.actions: list[list[np.ndarray]] = []
        self.scores: list[list[float]] = []
        self.frames: list[dict[int, np.ndarray]] = []

    def on_reset(self, state: StepResult) -> None:
        b = len(state.done)
        self.actions, self.frames = [[] for _ in range(b)], [{} for _ in range(b)]
        self.scores = [[s] for s in state.reward.float().cpu().tolist()]
        self._keep_frames(state)

    def on_step(self, actions: torch.Tensor, mu, beta, state: StepResult) -> None:
        acts, scores = actions.float().cpu().numpy(), state.reward.float().cpu().tolist()
        for r in range(len(acts)):
            self.actions[r].append(acts[r])
            self.scores[r].append(scores[r])
        self._keep_frames(state)

    def _keep_frames(self, state: StepResult) -> None:
        t = int(state.t[0])  # watched to the horizon: every rollout is at the same step
        for r in range(len(state.t)):
            if t in self.keep or r in self.full:
                self.frames[r][t] = state.frames[r].permute(1, 2, 0).cpu().numpy()


@torch.no_grad()
def imagine(policy, env: ImaginedEnv, contexts: list[Context], n_rollouts: int, encoder, generator: torch.Generator,
            noise_scale: float = 1.0, keep_steps=(), full_rollouts=()) -> list[ImaginedRun]:
    """`n_rollouts` imagined rollouts per context (context-major, as LOOP draws them), watched to
    the horizon: the env's threshold is lifted while they run, so the rollout that stopping at
    any eta would give is this one cut at its first check above eta (the policy's noise and the
    world model's draws do not depend on which rollouts are done). Frames are kept at
    `keep_steps` (multiples of the chunk) and at every chunk boundary of the rollouts whose index
    is in `full_rollouts` (side-by-side videos, further reflectors' verdicts)."""
    from worldenv_core.rl.loop import collect_rollouts

    keeper = _Keeper(set(int(s) for s in keep_steps), set(int(r) for r in full_rollouts))
    eta, env.eta = env.eta, 1.0  # R is a probability: never above 1, so nothing stops before the horizon
    try:
        batch = collect_rollouts(policy, env, contexts, n_rollouts, encoder, generator=generator, observer=keeper,
                                 noise_scale=noise_scale)
    finally:
        env.eta = eta
    return [ImaginedRun(context=r // n_rollouts, actions=np.concatenate(keeper.actions[r]).astype(np.float32),
                        scores=keeper.scores[r], steps=int(batch.t_end[r]), frames=keeper.frames[r])
            for r in range(len(contexts) * n_rollouts)]


def pair(run: ImaginedRun, real: dict, task_id: int, context_kind: str, policy: str, chunk: int) -> dict:
    """One row: the imagined rollout's scores beside the real outcome of its actions
    (`envs.replay.execute`, run to the same horizon). Eta-free: `judge` reads the verdicts."""
    return {"policy": policy, "task_id": task_id, "context": run.context, "context_kind": context_kind,
            "chunk": chunk, "steps": run.steps, "imagined_scores": [round(s, 5) for s in run.scores],
            "real_scores": [round(s, 5) for s in real["scores"]], "real_first_success": real["first_success"],
            "real_error": real["error"], "more_reflectors": {}}


def rescored(reflector, instruction: str, frames: np.ndarray, encoder, past=None) -> list[float]:
    """R after every check of a pair's side, from its frames at the checks (K, H, W, 3) uint8, as
    the incremental scorer of the imagined env or the replay gave it (same frames, same prefixes;
    `past`: a mid-episode context's recorded frames before them, `Context.history`)."""
    video = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)
    weights = next(reflector.parameters(), None)
    video = video.to(weights.device) if weights is not None else video
    scorer = reflector.scorer([instruction], encoder) if past is not None else None
    if scorer is None or not hasattr(scorer, "add_history"):  # one padded batch of every prefix
        return [round(float(s), 5) for s in reflector.score_prefixes(video, instruction, list(range(len(video))), encoder)]
    scorer.add_history([past.to(video.device)])
    out = []
    for k in range(len(video)):
        scorer.add(video[k:k + 1])
        out.append(round(float(scorer.score()[0]), 5))
    return out


def terminal_reward(scores: list[float], eta: float) -> float:
    """LOOP's reward of a rollout watched to the horizon: R at the first check above eta, else at the horizon."""
    return next((s for s in scores[1:] if s > eta), scores[-1])


def as_judged_by(row: dict, name: str) -> dict:
    """The row as further reflector `name` judges the same pair (its scores in `more_reflectors`)."""
    return {**row, **row["more_reflectors"][name]}


def judge(row: dict, eta: float) -> dict:
    """The verdicts at `eta`: imagination stops at the first check after a chunk with R > eta (as
    `ImaginedEnv` does), else at the horizon; imagined success = it stopped; the real outcome
    of the same actions = the oracle fired by that step; the reflector on the real frames is
    asked at the same check."""
    scores, chunk = row["imagined_scores"], row["chunk"]
    k = next((i for i in range(1, len(scores)) if scores[i] > eta), None)
    stop = row["steps"] if k is None else min(k * chunk, row["steps"])
    first = row["real_first_success"]
    real = row["real_scores"]
    at = len(scores) - 1 if k is None else k
    return {"imagined_success": k is not None, "imagined_reward": scores[at], "imagined_steps": stop,
            "real_success": row["real_error"] is None and first is not None and first <= stop,
            "real_first_success": first, "real_reward": real[min(at, len(real) - 1)] if real else float("nan")}


def verdict_metrics(rows: list[dict], eta: float, intervals: bool = False) -> dict:
    """How well the imagined verdict at `eta` predicts the real outcome of the same actions; `intervals`
    adds the 95 % intervals of AUROC and F1 (a bootstrap: for reported figures, not inside eta sweeps)."""
    if not rows:
        return {"rollouts": 0}
    judged = [judge(r, eta) for r in rows]
    real = np.array([j["real_success"] for j in judged], dtype=bool)
    said = np.array([j["imagined_success"] for j in judged], dtype=bool)
    imagined = binary_metrics([j["imagined_reward"] for j in judged], real, eta)
    on_real = binary_metrics([j["real_reward"] for j in judged], real, eta)
    timing = [j["imagined_steps"] - j["real_first_success"] for j in judged if j["imagined_success"] and j["real_success"]]
    own = reflector_on_real(rows, eta)
    n_imagined = imagined["tp"] + imagined["fp"]
    return {"rollouts": len(rows), "imagined_success": float(said.mean()), "real_success": float(real.mean()),
            "success_gap": float(said.mean() - real.mean()),
            "auroc": imagined["auroc"], "precision": imagined["precision"], "recall": imagined["recall"],
            "f1": imagined["f1"], "agreement": imagined["accuracy"],
            "hack_rate": imagined["fp"] / n_imagined if n_imagined else float("nan"),
            "hacks": imagined["fp"], "missed": imagined["fn"],
            "timing_error_mean": float(np.mean(timing)) if timing else float("nan"),
            "timing_error_median": float(np.median(timing)) if timing else float("nan"),
            "real_frames_auroc": on_real["auroc"], "real_frames_f1": on_real["f1"],
            "real_frames_precision": on_real["precision"], "real_frames_recall": on_real["recall"],
            **{f"real_stop_{k}": own[k] for k in ("auroc", "f1", "precision", "recall")},
            **mixed_groups(rows, said, real),
            **(context_intervals([j["imagined_reward"] for j in judged], real, eta, rows) if intervals else {})}


def misattributed(rows: list[dict]) -> list[bool]:
    """Which pairs have another context's real side: pairs made before a benchmark init state's start named
    its task ('init<k>', not 'task<t>/init<k>') where one run used that init state in more than one task.
    Those runs keyed the replays by start, so every task's imagined rollouts from it were paired with the
    replays of one task's actions; their real outcomes are void (the imagined side stands)."""
    legacy = [r.get("context_kind") == "init" and re.fullmatch(r"init\d+", str(r.get("start"))) is not None
              for r in rows]
    tasks: dict = {}
    for r in (r for r, old in zip(rows, legacy) if old):
        tasks.setdefault((r.get("policy"), r["start"]), set()).add(r.get("task_id"))
    return [old and len(tasks[(r.get("policy"), r["start"])]) > 1 for r, old in zip(rows, legacy)]


def context_key(row: dict) -> tuple:
    """Which context a paired rollout started from: its group for RLOO and for the bootstrap."""
    # the task too: a benchmark init state's start ('init0' in older pairs) is one per task
    return row.get("policy"), row.get("task_id"), row.get("context_kind"), row.get("start") or row["context"]


def context_intervals(reward, real: np.ndarray, eta: float, rows: list[dict]) -> dict:
    """95 % intervals of AUROC, F1 and the hack rate, resampling contexts (a context's rollouts share its start): with
    80 pairs from 20 contexts, what separates two world models and what is a new draw of rollouts."""
    reward = np.asarray(reward, dtype=float)
    contexts = [str(context_key(r)) for r in rows]
    on = lambda name: cluster_bootstrap_ci(  # noqa: E731
        lambda i: binary_metrics(reward[i], real[i], eta)[name], contexts)
    low, high = on("precision")  # the hack rate is 1 - precision
    return {"auroc_ci95": on("auroc"), "f1_ci95": on("f1"), "hack_rate_ci95": [1.0 - high, 1.0 - low]}


def mixed_groups(rows: list[dict], said: np.ndarray, real: np.ndarray) -> dict:
    """The fraction of contexts whose rollouts disagree, imagined and real: LOOP learns only from
    such groups (RLOO advantages of a group that agrees are zero, or the reward model's noise), so an
    imagination that agrees where reality does not gives the policy nothing to learn."""
    groups: dict = {}
    for i, r in enumerate(rows):
        groups.setdefault(context_key(r), []).append(i)
    multi = [g for g in groups.values() if len(g) > 1]
    if not multi:
        return {}
    mixed = lambda flags: float(np.mean([0 < flags[g].sum() < len(g) for g in multi]))  # noqa: E731
    return {"imagined_mixed_groups": mixed(said), "real_mixed_groups": mixed(real)}


def reflector_on_real(rows: list[dict], eta: float) -> dict:
    """The reflector terminating the *real* replays as it terminates imagined ones: success when
    any check's R on the real frames exceeds eta, against the oracle firing by the horizon
    (AUROC of the largest R). `real_frames_*` asks it at the imagined verdict's check instead,
    which, when imagination never stops, is the horizon: after an open-loop sequence has
    passed through success and gone on, the scene there no longer shows it."""
    truth = [r["real_error"] is None and r["real_first_success"] is not None and r["real_first_success"] <= r["steps"]
             for r in rows]
    best = [max(r["real_scores"][1:], default=float("nan")) for r in rows]
    return binary_metrics(best, np.array(truth, dtype=bool), eta)


ETA_GRID = tuple(float(e) for e in np.round(np.arange(0.05, 1.0, 0.05), 2))


def eta_curve(rows: list[dict], grid=ETA_GRID) -> list[dict]:
    """The agreement at every threshold (exact: the pairs were watched to the horizon), to see
    whether any eta would make the imagined verdict usable and what it would cost."""
    return [{"eta": e, **{k: verdict_metrics(rows, e)[k] for k in ("f1", "precision", "recall", "imagined_success",
                                                                    "real_success")}} for e in grid] if rows else []


def replay_eta(rows: list[dict], folds: int = 2, grid=ETA_GRID) -> dict:
    """eta chosen on paired replays instead of real frames (a lever of verdict fidelity): K-fold over
    contexts (a context's rollouts stay together); each fold is judged at the eta with the best
    F1 on the other folds' pairs, so the figures are never tuned on what they score. Exact: the
    rollouts were watched to the horizon, so the verdict at any eta is known."""
    from worldenv_core.rl.termination import best_eta

    contexts = sorted({r["context"] for r in rows})
    if len(contexts) < folds:
        return {"folds": folds, "etas": []}
    # folds by the context's rank, not its number: a subset (e.g. every other context) still splits evenly
    fold = {c: i % folds for i, c in enumerate(contexts)}
    judged, etas = [], []
    for k in range(folds):
        train = [r for r in rows if fold[r["context"]] != k]
        eta = best_eta({e: verdict_metrics(train, e)["f1"] for e in grid}, prior=0.5)
        etas.append(eta)
        judged.append(verdict_metrics([r for r in rows if fold[r["context"]] == k], eta))
    n = sum(j["rollouts"] for j in judged)
    out = {"folds": folds, "etas": etas}
    for key in ("f1", "precision", "hack_rate", "imagined_success", "real_success"):  # weighted by pairs
        vals = [(j[key], j["rollouts"]) for j in judged if not np.isnan(j[key])]
        out[key] = sum(v * w for v, w in vals) / sum(w for _, w in vals) if vals else float("nan")
    out["rollouts"] = n
    return out


def per_task(rows: list[dict], eta: float) -> dict[int, dict]:
    """Imagined and real success per task at `eta`."""
    out = {}
    for t in sorted({r["task_id"] for r in rows}):
        judged = [judge(r, eta) for r in rows if r["task_id"] == t]
        out[t] = {"rollouts": len(judged), "imagined_success": float(np.mean([j["imagined_success"] for j in judged])),
                  "real_success": float(np.mean([j["real_success"] for j in judged]))}
    return out


def frame_metrics(imagined: dict[int, np.ndarray], real: dict[int, np.ndarray]) -> dict[int, tuple[float, float]]:
    """step -> (PSNR, SSIM) of the imagined frame against the real one, where both exist."""
    steps = sorted(set(imagined) & set(real) - {0})
    if not steps:
        return {}
    fake = torch.from_numpy(np.stack([imagined[s] for s in steps])).permute(0, 3, 1, 2).float() / 255
    true = torch.from_numpy(np.stack([real[s] for s in steps])).permute(0, 3, 1, 2).float() / 255
    return {s: (float(p), float(q)) for s, p, q in zip(steps, psnr(fake, true), ssim(fake, true))}


def evaluator_metrics(per_policy: dict[str, dict], real_key: str = "closed_loop_success",
                      imagined_key: str = "imagined_success") -> dict:
    """The world model as a policy evaluator: rank correlation and mean absolute error between
    each policy's imagined success (or another imagined score, `imagined_key`) and its real
    success (`real_key`)."""
    names = [n for n, m in per_policy.items() if m.get(real_key) is not None and m.get(imagined_key) is not None]
    if len(names) < 2:
        return {"policies": len(names), "spearman": float("nan"), "mae": float("nan")}
    imagined = [per_policy[n][imagined_key] for n in names]
    real = [per_policy[n][real_key] for n in names]
    return {"policies": len(names), "spearman": spearman(imagined, real),
            "mae": float(np.mean(np.abs(np.subtract(imagined, real))))}
