"""Verdict fidelity: does the imagined environment judge a rollout as the real simulator would?

`imagine` runs a policy in the imagined environment exactly as LOOP does (`collect_rollouts`:
the same env, Laplace-sampled actions, reflector termination) and keeps, per rollout, the
actions it executed, its imagined verdict (success = stopped by R > eta, the step, R at the
stop) and the imagined frames at a few steps. `envs.replay` executes those actions in the real
simulator; `pair` joins both sides, and the functions below measure the agreement:

* `verdict_metrics`: AUROC of the imagined reward against the real outcome; precision, recall
  and F1 of imagined success at eta; the hack rate (imagined successes that fail in reality);
  the timing error; the same numbers for the reflector on the *real* frames of the same actions,
  which separates the world model's error from the reflector's;
* `frame_metrics`: PSNR / SSIM of imagined against real frames along the paired trajectories;
* `evaluator_metrics`: the world model as a policy evaluator (Spearman and MAE between imagined
  and real success over policies).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from worldenv_core.imagination.env import Context, ImaginedEnv, StepResult
from worldenv_core.metrics import binary_metrics, psnr, spearman, ssim


@dataclass
class ImaginedRun:
    """One imagined rollout: what the real simulator needs to replay it, and what imagination said."""

    context: int
    actions: np.ndarray  # (t_end, 7) float32, simulator units
    success: bool  # stopped by the reflector (R > eta)
    reward: float  # R at t_end: the reward LOOP would use
    steps: int  # t_end
    frames: dict[int, np.ndarray] = field(default_factory=dict)  # step -> (H, W, 3) uint8, chunk boundaries


class _Keeper:
    """A `collect_rollouts` observer: per rollout, the actions it executed while live and its
    imagined frames at the steps in `keep` (every chunk boundary for rollouts in `full`)."""

    def __init__(self, keep: set[int], full: set[int]):
        self.keep, self.full = keep, full
        self.actions: list[list[np.ndarray]] = []
        self.frames: list[dict[int, np.ndarray]] = []
        self.done: torch.Tensor | None = None

    def on_reset(self, state: StepResult) -> None:
        b = len(state.done)
        self.actions, self.frames = [[] for _ in range(b)], [{} for _ in range(b)]
        self._keep_frames(state, torch.ones(b, dtype=torch.bool))
        self.done = state.done.cpu().clone()

    def on_step(self, actions: torch.Tensor, mu, beta, state: StepResult) -> None:
        live = ~self.done
        acts = actions.float().cpu().numpy()
        for r in np.flatnonzero(live.numpy()):
            self.actions[r].append(acts[r])
        self._keep_frames(state, live)
        self.done = state.done.cpu().clone()

    def _keep_frames(self, state: StepResult, live: torch.Tensor) -> None:
        t = state.t.cpu()
        for r in np.flatnonzero(live.numpy()):
            if int(t[r]) in self.keep or r in self.full:
                self.frames[r][int(t[r])] = state.frames[r].permute(1, 2, 0).cpu().numpy()


@torch.no_grad()
def imagine(policy, env: ImaginedEnv, contexts: list[Context], n_rollouts: int, encoder, generator: torch.Generator,
            noise_scale: float = 1.0, keep_steps=(), full_rollouts=()) -> list[ImaginedRun]:
    """`n_rollouts` imagined rollouts per context (context-major, as LOOP draws them). Frames are
    kept at `keep_steps` (multiples of the chunk) and at every chunk boundary of the rollouts
    whose index is in `full_rollouts` (side-by-side videos)."""
    from worldenv_core.rl.loop import collect_rollouts

    keeper = _Keeper(set(int(s) for s in keep_steps), set(int(r) for r in full_rollouts))
    batch = collect_rollouts(policy, env, contexts, n_rollouts, encoder, generator=generator, observer=keeper,
                             noise_scale=noise_scale)
    runs = []
    for r in range(len(contexts) * n_rollouts):
        steps = int(batch.t_end[r])
        acts = np.concatenate(keeper.actions[r])[:steps] if keeper.actions[r] else np.zeros((0, 7), np.float32)
        runs.append(ImaginedRun(context=r // n_rollouts, actions=acts.astype(np.float32),
                                success=bool(batch.by_reflector[r]), reward=float(batch.rewards[r]), steps=steps,
                                frames=keeper.frames[r]))
    return runs


def pair(run: ImaginedRun, real: dict, eta: float, task_id: int, context_kind: str, policy: str) -> dict:
    """One row: the imagined verdict beside the real outcome of the same actions (`envs.replay.execute`)."""
    real_scores = real["scores"]
    stop = next((i for i, s in enumerate(real_scores) if s > eta), None)
    return {"policy": policy, "task_id": task_id, "context": run.context, "context_kind": context_kind,
            "imagined_success": run.success, "imagined_reward": run.reward, "imagined_steps": run.steps,
            "real_success": real["success"], "real_first_success": real["first_success"],
            "real_success_at_end": real["success_at_end"], "real_error": real["error"],
            # the reflector on the real frames of the same actions: R at the last one, and whether it would stop
            "real_reward": real_scores[-1] if real_scores else float("nan"),
            "real_reflector_success": stop is not None}


def verdict_metrics(rows: list[dict], eta: float) -> dict:
    """How well the imagined verdict predicts the real outcome of the same actions."""
    if not rows:
        return {"rollouts": 0}
    real = np.array([r["real_success"] for r in rows], dtype=bool)
    imagined = binary_metrics([r["imagined_reward"] for r in rows], real, eta)
    on_real = binary_metrics([r["real_reward"] for r in rows], real, eta)
    timing = [r["imagined_steps"] - r["real_first_success"] for r in rows
              if r["imagined_success"] and r["real_success"] and r["real_first_success"] is not None]
    n_imagined = imagined["tp"] + imagined["fp"]
    return {"rollouts": len(rows), "imagined_success": float(np.mean([r["imagined_success"] for r in rows])),
            "real_success": float(real.mean()),
            "success_gap": float(np.mean([r["imagined_success"] for r in rows]) - real.mean()),
            "auroc": imagined["auroc"], "precision": imagined["precision"], "recall": imagined["recall"],
            "f1": imagined["f1"], "agreement": imagined["accuracy"],
            "hack_rate": imagined["fp"] / n_imagined if n_imagined else float("nan"),
            "hacks": imagined["fp"], "missed": imagined["fn"],
            "timing_error_mean": float(np.mean(timing)) if timing else float("nan"),
            "timing_error_median": float(np.median(timing)) if timing else float("nan"),
            "real_frames_auroc": on_real["auroc"], "real_frames_f1": on_real["f1"],
            "real_frames_precision": on_real["precision"], "real_frames_recall": on_real["recall"]}


def per_task(rows: list[dict]) -> dict[int, dict]:
    """Imagined and real success per task."""
    out = {}
    for t in sorted({r["task_id"] for r in rows}):
        rs = [r for r in rows if r["task_id"] == t]
        out[t] = {"rollouts": len(rs), "imagined_success": float(np.mean([r["imagined_success"] for r in rs])),
                  "real_success": float(np.mean([r["real_success"] for r in rs]))}
    return out


def frame_metrics(imagined: dict[int, np.ndarray], real: dict[int, np.ndarray]) -> dict[int, tuple[float, float]]:
    """step -> (PSNR, SSIM) of the imagined frame against the real one, where both exist."""
    steps = sorted(set(imagined) & set(real) - {0})
    if not steps:
        return {}
    fake = torch.from_numpy(np.stack([imagined[s] for s in steps])).permute(0, 3, 1, 2).float() / 255
    true = torch.from_numpy(np.stack([real[s] for s in steps])).permute(0, 3, 1, 2).float() / 255
    return {s: (float(p), float(q)) for s, p, q in zip(steps, psnr(fake, true), ssim(fake, true))}


def evaluator_metrics(per_policy: dict[str, dict], real_key: str = "closed_loop_success") -> dict:
    """The world model as a policy evaluator: rank correlation and mean absolute error between
    each policy's imagined success and its real success (`real_key`)."""
    names = [n for n, m in per_policy.items() if m.get(real_key) is not None]
    if len(names) < 2:
        return {"policies": len(names), "spearman": float("nan"), "mae": float("nan")}
    imagined = [per_policy[n]["imagined_success"] for n in names]
    real = [per_policy[n][real_key] for n in names]
    return {"policies": len(names), "spearman": spearman(imagined, real),
            "mae": float(np.mean(np.abs(np.subtract(imagined, real))))}
