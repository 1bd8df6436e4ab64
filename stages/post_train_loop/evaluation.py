"""post_train_loop's evaluations and its section of the experiment report: the policy in the
real simulator, in imagination on fixed contexts and noise (so every evaluation point compares),
imagined rollouts recorded as MCAP, and the table and curves of the post-training runs."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from worldenv_core.contract import TaskContract
from worldenv_core.envs.collection import PolicyEvalJob, evaluate_policy_task
from worldenv_core.envs.libero_env import SCENE_SAMPLING
from worldenv_core.envs.replay import PairedReplayJob, RealStart, by_start, placement_starts, replay_context
from worldenv_core.envs.tasks import contract_task_ids, get_task
from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import StageRecord, sha256_file
from worldenv_core.parallel import default_workers, run_jobs
from worldenv_core.report import ReportContext, markdown_table, short_run, titled
from worldenv_core.imagination.env import WHOLE_DEPTH, Context, context_depth
from worldenv_core.imagination.recording import record_imagined_rollouts, write_imagined_rollouts
from worldenv_core.imagination.verdict import imagine, pair, terminal_reward, verdict_metrics
from worldenv_core.viz import plot_history


def with_gap(entry: dict) -> dict:
    """The imagined-vs-real gap where both were measured: the reflector's imagined success rate on
    the fixed contexts minus the real success rate (positive: imagination is too generous)."""
    if "real_success" in entry and "imagined_success" in entry:
        entry["imagined_real_gap"] = entry["imagined_success"] - entry["real_success"]
    return entry


def _fixed_picks(contexts: list, n: int, seed: int) -> tuple[list[int], torch.Generator]:
    """The indices of `n` contexts and the noise generator, the same at every evaluation point."""
    g = torch.Generator().manual_seed(seed)
    return torch.randperm(len(contexts), generator=g)[:min(n, len(contexts))].tolist(), g


@dataclass(frozen=True)
class PairedCheck:
    """Replay the imagined rollouts of the first `contexts` evaluation contexts in the real
    simulator (`starts`: where each training context starts there)."""
    contract: TaskContract
    starts: list[RealStart]
    contexts: int
    workers: int | None = None
    progress: bool = False


def imagined_success(policy, env, contexts: list[Context], n_contexts: int, n_rollouts: int, encoder, seed: int,
                     paired: PairedCheck | None = None) -> dict:
    """The policy in imagination on a fixed set of contexts with fixed noise: the same rollouts'
    worth of randomness for the SFT and every later policy, so the numbers are comparable and
    show whether post-training improved the objective it optimises (mean reward, reflector
    success rate), whatever the real simulator says. With `paired`, the actions of some of those
    rollouts are executed in the real simulator too: how often the policy's own imagined
    successes are real (the hack rate; real episodes, monitoring only)."""
    picks, g = _fixed_picks(contexts, n_contexts, seed + 7_777)
    runs = imagine(policy, env, [contexts[i] for i in picks], n_rollouts, encoder, g)  # LOOP's verdicts, read off
    out = {"imagined_reward": float(np.mean([terminal_reward(r.scores, env.eta) for r in runs])),
           "imagined_success": float(np.mean([any(s > env.eta for s in r.scores[1:]) for r in runs]))}
    if paired is None or not paired.contexts:
        return out
    chosen = picks[:paired.contexts]
    jobs = [PairedReplayJob(paired.contract, paired.starts[i], actions=tuple(runs[k * n_rollouts + j].actions
                                                                             for j in range(n_rollouts)),
                            keep=((),) * n_rollouts) for k, i in enumerate(chosen)]
    real = by_start(run_jobs(replay_context, jobs, workers=paired.workers, desc="paired replay",
                             progress=paired.progress, unit="ctx"))
    rows = [pair(runs[k * n_rollouts + j], real[paired.starts[i].key]["replays"][j], paired.starts[i].task_id, "episode",
                 "policy", env.chunk) for k, i in enumerate(chosen) for j in range(n_rollouts)]
    m = verdict_metrics(rows, env.eta)
    return {**out, "paired_hack_rate": m["hack_rate"], "paired_f1": m["f1"], "paired_real_success": m["real_success"],
            "paired_imagined_success": m["imagined_success"], "paired_episodes": len(rows),
            # do the policy's imagined groups disagree where its real ones do (LOOP's learning signal)?
            **{f"paired_{k}_mixed": m[f"{k}_mixed_groups"] for k in ("imagined", "real") if f"{k}_mixed_groups" in m}}


def record_imagined(policy, env, contexts: list[Context], n_contexts: int, contract: TaskContract, encoder,
                    camera: str, out_dir: Path, extra: dict, seed: int) -> list[Path]:
    """A few imagined rollouts of the policy, every frame, written as MCAP episodes (the same
    fixed contexts and noise at every evaluation, so the files show what training changed)."""
    picks, g = _fixed_picks(contexts, n_contexts, seed + 9_999)
    picked = [contexts[i] for i in picks]
    names = {t: get_task(contract.suite, t).name for t in {c.task_id for c in picked}}
    rollouts = record_imagined_rollouts(policy, env, picked, 2, encoder, contract.suite, names, camera, extra=extra,
                                        generator=g, fps=contract.control_freq)
    return write_imagined_rollouts(rollouts, out_dir, env.eta)


def real_success(policy_path: str, contract: TaskContract, init_states: int, workers, progress: bool) -> float:
    """Success in the real simulator (oracle termination) on the first benchmark init states."""
    jobs = [PolicyEvalJob(policy_path=policy_path, contract=contract, task_id=t, init_ids=tuple(range(init_states)),
                          termination="oracle") for t in contract_task_ids(contract)]
    rows = [r for out in run_jobs(evaluate_policy_task, jobs, workers=workers, desc="real-sim eval",
                                  progress=progress, unit="task") for r in out["rows"]]
    return sum(r["success"] for r in rows) / len(rows)


def validation_key(policy_path: str, contract: TaskContract, episodes: int) -> str | None:
    """What a validation result depends on: the policy's weights, the task contract, the set's size (the
    set itself follows from them) and how a reset draws a scene; None for a policy without a weights file."""
    weights = Path(policy_path) / "model.safetensors"
    if not weights.exists():
        return None
    what = {"weights": sha256_file(weights), "contract": dataclasses.asdict(contract), "episodes": int(episodes),
            "scenes": SCENE_SAMPLING}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def validation_jobs(policy_path: str, contract: TaskContract, episodes: int, workers: int) -> list[PolicyEvalJob]:
    """The validation set's episodes as worker jobs: a job per task, or per part of one where there
    are fewer tasks than workers (one task trained on: its 100 placements would run on one core)."""
    tasks = contract_task_ids(contract)
    by_task: dict[int, list[int]] = {t: [] for t in tasks}
    for st in placement_starts(contract.suite, tasks, episodes, "validation"):
        by_task[st.task_id].append(st.seed)
    parts = -(-max(1, workers) // max(1, len(tasks)))
    return [PolicyEvalJob(policy_path=policy_path, contract=contract, task_id=t, init_ids=(), termination="oracle",
                          placements=tuple(seeds[k::parts])) for t, seeds in by_task.items() for k in range(parts)
            if seeds[k::parts]]


def validation_success(policy_path: str, contract: TaskContract, episodes: int, workers, progress: bool,
                       cache: Path | None = None) -> dict:
    """Success (mean actions, oracle termination) on the fixed validation set: `episodes` fresh
    placements spread evenly over the tasks trained on, the same at every evaluation and in every
    run, never a benchmark init state nor a training context (`envs.placements`). What a recipe
    is judged by: training rollouts' success moves with the contexts an iteration drew. With
    `cache` (a folder), a policy already validated there (the same weights, contract and set: every
    new run's iteration 0, the SFT policy) is read back instead of run again: the episodes are
    deterministic, and none are consumed (`validation_episodes` 0, `validation_cached` 1)."""
    key = validation_key(policy_path, contract, episodes) if cache is not None else None
    if key is not None and (cache / f"{key}.json").exists():
        return {**json.loads((cache / f"{key}.json").read_text()), "validation_episodes": 0, "validation_cached": 1.0}
    jobs = validation_jobs(policy_path, contract, episodes, workers or default_workers())
    tasks = {j.task_id for j in jobs}
    rows = [r for out in run_jobs(evaluate_policy_task, jobs, workers=workers, desc="validation",
                                  progress=progress, unit="job") for r in out["rows"]]
    per_task = {f"validation_task{t}": float(np.mean([r["success"] for r in rows if r["task_id"] == t]))
                for t in sorted(tasks)}  # scalars, one curve each in the tracker
    out = {"validation_success": sum(r["success"] for r in rows) / len(rows), **per_task, "validation_episodes": len(rows)}
    if key is not None:
        cache.mkdir(parents=True, exist_ok=True)
        write_text_atomic(cache / f"{key}.json", json.dumps(out))
    return out


def imagined_span(loop: StageRecord) -> str:
    """The imagined evaluation on fixed contexts and noise: first and last evaluation point."""
    rew, ok = loop.metrics.get("imagined_reward", {}), loop.metrics.get("imagined_success", {})
    if len(rew) < 2:
        return "not run"
    a, b = min(rew, key=int), max(rew, key=int)
    return f"{rew[a]:.3f} -> {rew[b]:.3f}, {ok[a]:.3f} -> {ok[b]:.3f}"


def _span(history: list[dict], key: str, n: int = 5) -> str:
    """Mean of `key` over the first and the last n iterations: 'first -> last'."""
    vals = [h[key] for h in history if key in h and h.get("step", 0) > 0]
    if not vals:
        return ""
    k = min(n, max(1, len(vals) // 2))
    return f"{sum(vals[:k]) / k:.3g} -> {sum(vals[-k:]) / k:.3g}"


def section(ctx: ReportContext, limit: int = 6) -> list[str]:
    """One row per recent post_train_loop run: its settings, which world model and reflector it
    imagined with (so the "without extra data" ablation shows as its own row), and how the
    imagined reward, the reflector's success rate and the real success moved; the curves of the
    newest run that measured real success during training (the paper's Figure 3)."""
    runs = ctx.find("post_train_loop")[-limit:]
    if not runs:
        return []
    rows = []
    for r in runs:
        h = ctx.history(r)
        curve = ", ".join(f"{k}: {100 * v:.0f} %" for k, v in sorted(r.metrics.get("real_success", {}).items(),
                                                                     key=lambda kv: int(kv[0]))) or "not run"
        real = r.tags.get("env") == "real"  # the reference: no world model, the oracle as reward
        rows.append([env_label(r), r.tags.get("eta"), r.tags.get("n_rollouts"), r.metrics.get("iterations"),
                     "none" if real else ctx.input_tags(r, "train_worldsim").get("data", "?"),
                     "oracle" if real else ctx.input_tags(r, "train_reflector").get("data", "?"),
                     _span(h, "mean_reward"), _span(h, "reflector_success_rate"), _span(h, "episode_length"),
                     imagined_span(r), curve, f"{r.wall_time_s:.0f}"])
    lines = markdown_table(["env", "eta", "N", "iterations", "world model data", "reflector data",
                            "imagined reward (first 5 -> last 5 it.)", "reflector success rate", "episode length",
                            "fixed contexts: imagined reward, success (SFT -> last)", "real success by iteration",
                            "wall s"], rows)
    shown = next((r for r in reversed(runs) if len(r.metrics.get("real_success", {})) > 1), runs[-1])
    history = ctx.history(shown)
    if history:  # redrawn from the run's log, so older runs get the current layout too
        name = short_run(str(shown.files("plot")[0].path))
        plot_history(history, ctx.out / "post_training.png", f"post_train_loop {name}")
        lines += ["", f"![post-training curves of `{name}`](post_training.png)"]
    sweeps = [r.tags["sweep"] for r in ctx.find("post_train_loop") if r.tags.get("sweep")]
    if sweeps:  # the newest sweep over eta and N
        from stages.post_train_loop.sweep import plot_summary, summary_rows, summary_table

        rows = summary_rows([r for r in ctx.find("post_train_loop") if r.tags.get("sweep") == sweeps[-1]])
        plot_summary(rows, ctx.out / "sweep.png")
        lines += ["", f"Sweep `{sweeps[-1]}` over eta and N (`-m eta=... rl.n_rollouts=...`; each measure at the SFT "
                  "policy and after the last iteration):", "", *summary_table(rows), "", "![sweep](sweep.png)"]
    routes = [r for r in runs if len(r.metrics.get("real_success", {})) > 1]
    if {r.tags.get("env", "imagined") for r in routes} == {"imagined", "real"}:
        plot_routes(ctx, routes, ctx.out / "routes.png")
        lines += ["", "The imagined route against the real-simulator reference (`env=real`: the same LOOP with the "
                  "oracle as reward), by iteration and by the real-simulator episodes each consumed (collections "
                  "it used, plus the reference's own rollouts; evaluation episodes not counted):", "",
                  "![imagined vs real route](routes.png)"]
    return titled("Post-training (LOOP in imagination)", lines)


def env_label(run: StageRecord) -> str:
    """The run's environment, and where its rollouts start when not at the episodes' first frames."""
    rl = run.config.get("rl") or {}
    mid, depth = rl.get("mid_episode_frames"), context_depth(rl)
    at = f" at {depth[0]:g}-{depth[1]:g} of the way" if depth != WHOLE_DEPTH else ""
    return run.tags.get("env", "imagined") + (f", {mid} mid-episode frames{at}" if mid else "")


def real_episodes_used(ctx: ReportContext, run: StageRecord) -> tuple[int, int]:
    """(real episodes of the collections the run used, real episodes per iteration of its own)."""
    collected = sum(ctx.by_id[i].metrics.get("real_episodes") or 0 for i in run.inputs
                    if i in ctx.by_id and ctx.by_id[i].stage == "collect")
    per_iteration = (run.metrics.get("train_real_episodes") or 0) / max(1, run.metrics.get("iterations") or 1)
    return collected, int(per_iteration)


def plot_routes(ctx: ReportContext, runs: list[StageRecord], path: Path) -> Path:
    """Real success against the iteration, and against the real episodes consumed, for each run."""
    from worldenv_core.viz import figure, save_figure

    fig, axes = figure(ncols=2, figsize=(10, 3.8))
    for r in runs:
        curve = sorted((int(k), v) for k, v in r.metrics["real_success"].items())
        collected, per_it = real_episodes_used(ctx, r)
        label = f"{env_label(r)} eta {r.tags.get('eta')} N {r.tags.get('n_rollouts')}"
        if r.tags.get("env", "imagined") == "imagined" and r.config.get("reflector_from"):  # routes differ by their judge
            judge = Path(str(r.config["reflector_from"]))  # a released folder by its name, a work dir by its run
            label += f", {judge.name if judge.parent.parent.name == 'checkpoints' else short_run(str(judge))}"
        if not (r.config.get("rl") or {}).get("filter_groups", True):
            label += ", groups unfiltered"
        style = "-o" if r.tags.get("env") == "real" else "-s"
        axes[0].plot([i for i, _ in curve], [100 * v for _, v in curve], style, label=label, ms=3)
        axes[1].plot([collected + per_it * i for i, _ in curve], [100 * v for _, v in curve], style, label=label, ms=3)
    axes[0].set(xlabel="iteration", ylabel="real success (%)")
    axes[1].set(xlabel="real-simulator episodes consumed", ylabel="real success (%)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_pack_runs(histories: dict[str, str | Path], path: str | Path, title: str = "", paired: bool = True) -> Path:
    """LOOP runs side by side (work dirs' training.json, or a history.json kept from older runs), by
    iteration: imagined success (reflector > eta), groups kept and mean reward, each raw (faint)
    and as a 9-iteration running mean. Runs on one pack with one seed draw the same contexts at the
    same iteration, so their curves share a shape. `paired`: runs 1-2 solid, 3-4 dashed in the same
    two colours (two settings x two variants); otherwise a colour a run (seeds of one setting)."""
    import json

    from worldenv_core.viz import figure, save_figure

    panels = [("reflector_success_rate", "imagined success (reflector > eta) per iteration"),
              ("kept_groups", "groups kept (verdicts split)"), ("mean_reward", "mean reward R at t_end")]
    fig, axes = figure(1, len(panels), figsize=(14, 3.6))
    for i, (label, file) in enumerate(histories.items()):
        steps = [h for h in json.loads(Path(file).read_text()) if "mean_reward" in h]
        it = np.array([h["step"] for h in steps])
        colour, style = (f"C{i % 2}", "-" if i < 2 else "--") if paired else (f"C{i}", "-")
        for ax, (key, name) in zip(axes, panels):
            v = np.array([h[key] for h in steps])
            k = min(9, len(v))
            mean = np.convolve(v, np.ones(k) / k, mode="valid")
            ax.plot(it, v, alpha=0.12, color=colour, ls=style)
            ax.plot(it[k // 2: k // 2 + len(mean)], mean, label=label, color=colour, ls=style)
            ax.set_title(name, fontsize=9)
            ax.set_xlabel("LOOP iteration")
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)
