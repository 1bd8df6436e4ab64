"""Learning curves of LOOP runs against the real episodes they consumed, and the real route's throughput.

A recipe is judged on the fixed validation set of fresh placements (`eval.validation`), never on
the training rollouts' success, which moves with the contexts an iteration drew; both are drawn,
with how far each update moved the policy (exact KL, RMS change of the mean action) and whether
its batch was large enough for its direction to be the reward's (`direction_cosine`). Works on
finished and running runs alike (a running one's history is read from its last checkpoint), and
keeps each run's curve as JSON under results/ so it outlives the machine.

    python -m analysis.rl_curves --run trust_region_seed0=outputs/libero_spatial-small/post_train_loop/<hash> \\
        --json results/rl_recipes --figure docs/img/rl_curves_libero_spatial.png --markdown results/rl_recipes/curves.md
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from worldenv_core.files import write_text_atomic

# rollout time parts as real_rollout measures them (seconds summed over an iteration's rollouts)
PARTS = ("reset", "render", "policy", "physics", "env_build")


def read_history(work: str | Path) -> list[dict]:
    """A run's history: training.json when it finished, else its last checkpoint's; a kept ES ledger
    folder (`es_update.export_ledger`): the history it was exported with."""
    work = Path(work)
    if kept_ledger(work):
        return json.loads((work / "history.json").read_text())
    if (work / "training.json").exists():
        return json.loads((work / "training.json").read_text())
    last = work / "checkpoints" / "last"
    if not last.exists():
        raise FileNotFoundError(f"{work} holds neither training.json nor a checkpoint: not a post_train_loop work dir")
    import torch

    from worldenv_core.training.checkpoints import TRAIN_STATE

    return list(torch.load(last.resolve() / TRAIN_STATE, weights_only=False)["history"])


def kept_ledger(path: str | Path) -> bool:
    """An exported ES ledger (a run's state kept in the repository) rather than a work dir."""
    path = Path(path)
    return (path / "history.json").exists() and any(path.glob("iter_*.json"))


def es_ledger(work: str | Path) -> list[dict]:
    """An ES run's ledger (`es_ledger/iter_NNNN.json`, or a kept ledger folder itself; none for a PPO run)."""
    from worldenv_core.rl.es import read_ledger

    folder = Path(work) if kept_ledger(work) else Path(work) / "es_ledger"
    return read_ledger(folder) if folder.is_dir() else []


def consumed(steps: list[dict], rollouts_per_iteration: int):
    """step -> the real episodes the run's training consumed up to it. An iteration that recorded its count (ES:
    `train_episodes`, 0 in imagination) with the paired-replay guard's (`guard_episodes`) counts those; an older
    history's iteration counts its rollouts (every one real in the real route, where nothing else was recorded)."""
    def real(h: dict) -> float:
        return h.get("train_episodes", rollouts_per_iteration) + h.get("guard_episodes", 0)
    totals, running = {0: 0.0}, 0.0
    for h in sorted(steps, key=lambda h: h["step"]):
        running += real(h)
        totals[h["step"]] = running
    return lambda step: int(totals[max(k for k in totals if k <= step)])


def summarise(history: list[dict], rollouts_per_iteration: int, ledger: list[dict] | None = None) -> dict:
    """Per-iteration series and the throughput of the iterations' rollouts; with an ES run's `ledger`, whether
    its directions' effects repeat on other starts (`es.half_agreement`, in the direction-cosine column)."""
    steps = [h for h in history if "mean_reward" in h]
    spent = consumed(steps, rollouts_per_iteration)
    val = [(spent(h["step"]), h["validation_success"]) for h in history if "validation_success" in h]
    val_n = [h.get("validation_episodes", 0) for h in history if "validation_success" in h]
    per_task = {int(k[len("validation_task"):]): [(spent(h["step"]), h[k]) for h in history if k in h]
                for k in sorted({k for h in history for k in h if k.startswith("validation_task")})}
    series = {k: [(h["step"], h[k]) for h in steps if k in h]
              for k in ("mean_reward", "kept_groups", "exact_kl", "action_shift_rms", "direction_cosine", "ppo_steps",
                        "first_step_kl", "es_pair_diff_abs", "es_return_std", "es_step_rms")}
    wall = sum(h.get("seconds", 0.0) for h in steps)
    episodes = spent(steps[-1]["step"]) if steps else 0
    rollouts = len(steps) * rollouts_per_iteration  # the throughput's unit: real or imagined, as the run made them
    parts = {p: sum(h.get(f"rollout_{p}_seconds", 0.0) for h in steps) for p in PARTS}
    busy = sum(h.get("rollout_total_seconds", 0.0) for h in steps)
    update = sum(h.get("update_seconds", 0.0) for h in steps)
    # each iteration's |s|^2 and sigma^2 estimates are unbiased but noisy: pooled over iterations they say how
    # many mixed groups one update needs for its direction to be the reward's (rl.loop.gradient_signal)
    sig = [h["gradient_signal_sq"] for h in steps if "gradient_signal_sq" in h]
    noise = [h["gradient_noise_sq"] for h in steps if "gradient_noise_sq" in h]
    pooled = (sum(sig) / len(sig), sum(noise) / len(noise)) if sig else None
    groups_needed = (0.81 / 0.19) * pooled[1] / pooled[0] if pooled and pooled[0] > 0 else None
    if ledger:
        from worldenv_core.rl.es import half_agreement

        # a context's task is its placement number mod the task count (the validated tasks: the run's); each task's
        # starts split between the halves, as the even/odd positions of a multi-task iteration would split its tasks
        n_tasks, discount = max(1, len(per_task)), ledger[0].get("es_discount") or 1.0
        agree = half_agreement(ledger, discount, n_tasks=n_tasks)
        series["direction_cosine"] = [(e["iteration"], c) for e, c in zip(ledger, agree["per_iteration"])]
        series["es_half_cosine_pooled"] = agree["pooled"]
        if n_tasks > 1:  # does a direction that helps some tasks help the others?
            across = half_agreement(ledger, discount, n_tasks=n_tasks, across_tasks=True)
            if across["pooled"] == across["pooled"]:  # NaN where each iteration held one task (rl.task_focus=1)
                series["es_half_cosine_across_tasks"] = across["pooled"]
    return {"iterations": len(steps), "real_rl_episodes": episodes, "validation": val, "validation_episodes": val_n,
            "validation_tasks": per_task, **series,
            "gradient_signal": {"iterations": len(sig), "signal_sq": pooled[0] if pooled else None,
                                "noise_sq": pooled[1] if pooled else None, "groups_for_cos_0.9": groups_needed},
            "throughput": {"episodes_per_hour": rollouts / wall * 3600 if wall else None,
                           "hours_per_1000_episodes": wall / rollouts * 1000 / 3600 if rollouts else None,
                           "iteration_seconds": wall / len(steps) if steps else None,
                           # shares of the rollouts' worker time, and the PPO update's share of the wall time
                           "rollout_share": {p: v / busy for p, v in parts.items()} if busy else {},
                           "update_share_of_wall": update / wall if wall else None}}


def _task_bars(ax, per_task: dict) -> None:
    """Each task's validation success at the run's first and last validation point, side by side."""
    tasks = sorted(per_task)
    if not tasks or not all(per_task[t] for t in tasks):
        return
    for k, (which, shade) in enumerate(((0, "#bbbbbb"), (-1, "#1f77b4"))):
        at = per_task[tasks[0]][which][0]
        ax.bar([t + (k - 0.5) * 0.4 for t in tasks], [per_task[t][which][1] for t in tasks], width=0.4, color=shade,
               label=f"{at} RL episodes")
    ax.set_xticks(tasks)
    ax.legend(fontsize=8)


def plot(runs: dict[str, dict], path: str | Path, title: str = "") -> Path:
    """Validation success against real RL episodes, and the per-iteration diagnostics, one line per run."""
    from worldenv_core.viz import figure, save_figure

    fig, axes = figure(2, 3, figsize=(15, 7.5), squeeze=False)
    ppo = any(s.get("exact_kl") or s.get("action_shift_rms") for s in runs.values())
    panels = [("validation success (fixed fresh placements)", "validation", "real RL episodes consumed"),
              ("training rollouts' success (diagnostic)", "mean_reward", "iteration"),
              ("exact KL per update (PPO)", "exact_kl", "iteration"),
              ("direction cosine (PPO: even vs odd groups; ES: two halves of each task's starts)", "direction_cosine", "iteration"),
              ("weight-space members: mean |R+ - R-| per pair (ES)", "es_pair_diff_abs", "iteration"),
              ("RMS change of the mean action (PPO)", "action_shift_rms", "iteration")]
    if not ppo:  # ES runs only: the PPO panels would be empty, so per-task validation and the step's size instead
        first = next(iter(runs))
        panels[2] = (f"validation per task, {first}: first and last point", "validation_tasks", "task")
        panels[5] = ("ES step, RMS relative to each weight tensor", "es_step_rms", "iteration")
    for ax, (name, key, xlabel) in zip(axes.flat, panels):
        if key == "validation_tasks":  # the first run's per-task bars, not a line per run
            _task_bars(ax, next(iter(runs.values())).get(key) or {})
        for label, s in (runs.items() if key != "validation_tasks" else ()):
            pts = s.get(key) or []
            if pts and key == "validation":  # with the 95 % binomial interval of each point's episodes
                err = [1.96 * math.sqrt(y * (1 - y) / n) if n else 0.0 for (_, y), n in zip(pts, s["validation_episodes"])]
                ax.errorbar([x for x, _ in pts], [y for _, y in pts], yerr=err, marker="o", ms=4, capsize=3, label=label)
            elif pts:  # markers: a run of one iteration shows too
                ax.plot([x for x, _ in pts], [y for _, y in pts], label=label, marker="o", markersize=3)
        if key in ("validation", "mean_reward", "validation_tasks"):
            ax.set_ylim(0, 1)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].axhline(0.0, color="grey", lw=0.8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def markdown(runs: dict[str, dict]) -> str:
    """One row per run: budget, validation first -> last, update size, batch direction, throughput."""
    def fmt(x, spec=".3f"):
        return "" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)

    def mean(pts):  # an iteration whose halves left nothing to compare reads NaN (undefined, not zero): skipped
        ys = [y for _, y in pts if not (isinstance(y, float) and math.isnan(y))]
        return sum(ys) / len(ys) if ys else None
    rows = ["| run | iterations | real RL episodes | validation (real episodes: success) | mean exact KL | "
            "mean direction cosine | mixed groups for cos 0.9 (pooled) | rollouts / hour |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, s in runs.items():
        val = ", ".join(f"{x}: {y:.2f}" for x, y in s["validation"])
        rows.append(f"| {label} | {s['iterations']} | {s['real_rl_episodes']} | {val} | {fmt(mean(s['exact_kl']), '.4f')} | "
                    f"{fmt(mean(s['direction_cosine']))} | {fmt(s['gradient_signal']['groups_for_cos_0.9'], '.0f')} | "
                    f"{fmt(s['throughput']['episodes_per_hour'], '.0f')} |")
    return "\n".join(rows) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=WORKDIR",
                    help="a post_train_loop work dir, or a kept ES ledger folder, named (repeatable)")
    ap.add_argument("--rollouts", type=int, default=None,
                    help="rollouts per iteration (default: from the work dir's run_config.json)")
    ap.add_argument("--json", type=Path, help="a folder: each run's curve as NAME.json")
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--title", default="")
    args = ap.parse_args(argv)
    runs = {}
    for spec in args.run:
        if "=" not in spec:
            ap.error(f"--run wants NAME=WORKDIR, got {spec!r}")
        name, work = spec.split("=", 1)
        runs[name] = summarise(read_history(work), args.rollouts or rollouts_of(work), es_ledger(work))
    if args.json:
        args.json.mkdir(parents=True, exist_ok=True)
        for name, s in runs.items():
            write_text_atomic(args.json / f"{name}.json", json.dumps(s, indent=1))
    if args.figure:
        plot(runs, args.figure, args.title)
    text = markdown(runs)
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.markdown, text)
    print(text)
    return runs


def rollouts_of(work: str | Path) -> int:
    """Rollouts per iteration of a run: contexts x N (ES: contexts x 2 x pairs) from the resolved config
    post_train_loop keeps in its work dir (`run_config.json`), or a kept ledger's shape (contexts x members)."""
    if kept_ledger(work):
        first = es_ledger(work)[0]["success"]
        return len(first) * len(first[0])
    path = Path(work) / "run_config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} missing: pass --rollouts (contexts_per_iteration x n_rollouts)")
    rl = json.loads(path.read_text())["rl"]
    if rl.get("policy_update") == "es":  # both members of each weight-space pair from every context
        return int(rl["contexts_per_iteration"]) * 2 * int(rl["es_pairs"])
    return int(rl["contexts_per_iteration"]) * int(rl["n_rollouts"])


if __name__ == "__main__":
    main()
