"""evaluate's results and its sections of the experiment report: success per task in the real
simulator, SFT vs post-trained under oracle / fixed / reflector termination (the paper's Tables 1
and 3) with the paired McNemar test, evaluations on other suites, episode videos, and the
ablations as far as they were run (the paper's Table 2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.post_train_loop.evaluation import imagined_span
from worldenv_core.evaluations import checkpoint_name
from worldenv_core.manifest import StageRecord
from worldenv_core.stats import paired_success_test
from worldenv_core.report import POLICIES, TERMINATIONS, ReportContext, markdown_table, newest, short_run, titled
from worldenv_core.rl.termination import StopOutcome, termination_metrics
from worldenv_core.viz import figure, montage_video, save_figure, video_picks


def summarise(rows: list[dict]) -> dict:
    per_task = []
    for tid in sorted({r["task_id"] for r in rows}):
        rs = [r for r in rows if r["task_id"] == tid]
        per_task.append({"task_id": tid, "task": rs[0]["task"], "n": len(rs),
                         "success_rate": float(np.mean([r["success"] for r in rs])),
                         "ever_succeeded_rate": float(np.mean([r["ever_succeeded"] for r in rs])),
                         "mean_steps": float(np.mean([r["steps"] for r in rs])),
                         "errors": sum(r["error"] is not None for r in rs)})
    return {"success_rate": float(np.mean([r["success"] for r in rows])),
            "ever_succeeded_rate": float(np.mean([r["ever_succeeded"] for r in rows])),
            "episodes": len(rows), "per_task": per_task}


def init_span(summary: dict) -> str:
    """Which init states an evaluation ran: "first 20", or "20-49" for a later range."""
    first, n = summary.get("first_init_state", 0), summary["init_states"]
    return f"first {n}" if not first else f"{first}-{first + n - 1}"


def markdown(summary: dict, suite: str) -> str:
    """One evaluation's results.md."""
    rows = [[r["task_id"], r["task"], f"{100 * r['success_rate']:.0f}%", f"{100 * r['ever_succeeded_rate']:.0f}%",
             f"{r['mean_steps']:.0f}"] for r in summary["per_task"]]
    rows.append(["all", "", f"**{100 * summary['success_rate']:.1f}%**", f"{100 * summary['ever_succeeded_rate']:.1f}%", ""])
    lines = [f"Success on {suite} ({summary['termination']} termination, {init_span(summary)} "
             f"benchmark init states per task)\n",
             *markdown_table(["task", "name", "success", "reached success at some step", "mean steps"], rows)]
    if "reflector_termination" in summary:
        t = summary["reflector_termination"]
        early = t["false_stops_before_success"]
        lines += ["", f"Reflector stops (eta = {summary['eta']}): {t['correct_stops']} at or after the oracle's success "
                  f"(median {t['timing_error_median']:.0f} steps late), {t['false_stops']} false stops "
                  f"({early} before a success that came later, {t['false_stops'] - early} in failures), "
                  f"{t['missed_successes']} successes never stopped; termination F1 {t['f1']:.3f}."]
    return "\n".join(lines) + "\n"


def record_mode(stage, mode: str, rows: list[dict], videos: dict, setting: dict, reflector_path: str | None,
                eta: float | None, out_dir: Path) -> dict:
    """Write one termination mode's results, episodes and videos, and fill its manifest record.
    `setting`: policy, init_states, suite and max_steps of the evaluation."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarise(rows)
    suite = setting["suite"]
    summary.update(policy=setting["policy"], policy_digest=setting["policy_digest"], termination=mode,
                   init_states=setting["init_states"], first_init_state=setting["first_init_state"],
                   report_dir=str(out_dir), suite=suite, max_steps=setting["max_steps"])
    if mode == "reflector":
        summary.update(reflector=reflector_path, eta=eta, reflector_termination=termination_metrics(
            [StopOutcome(r["first_success_step"], r["stop_step"]) for r in rows if r["error"] is None]))
    (out_dir / "episodes.json").write_text(json.dumps(rows, indent=1))
    (out_dir / "results.json").write_text(json.dumps(summary, indent=2))
    (out_dir / "results.md").write_text(markdown(summary, suite))
    for name in ("results.json", "results.md", "episodes.json"):
        stage.add_output(out_dir / name, kind="report")
    for (tid, i), frames in sorted(videos.items()):
        r = next(r for r in rows if r["task_id"] == tid and r["init_state"] == i)
        # the episode up to where this mode stopped (fixed: the horizon), as many frames as a GIF plays: the
        # job rendered just those (frame index -> image; an array in jobs kept before it did, read the same)
        frames = np.stack([frames[j] for j in video_picks(r["steps"] + 1)])
        path = montage_video([frames], out_dir / "videos" / f"task{tid:02d}_init{i:02d}_{'success' if r['success'] else 'failure'}.gif")
        stage.add_output(path, kind="video")
    stage.metrics.update({k: v for k, v in summary.items() if k != "per_task"})
    print(markdown(summary, suite))
    return summary


def own_suite_evaluations(ctx: ReportContext, **tags) -> list[StageRecord]:
    """The task's evaluations of the first N init states on its own suite (those on another suite
    carry an `eval_suite` tag and have their own table; those through a world model's view a `view`
    tag: diagnostics; those of a later range a `first_init_state` tag: pooled by `paired`)."""
    return [r for r in ctx.find("evaluate", **tags) if not {"eval_suite", "view", "first_init_state"} & set(r.tags)]


def success_table(ctx: ReportContext) -> tuple[list[str], dict]:
    """Success per task, one column per (policy, termination), newest evaluation of each."""
    evals = own_suite_evaluations(ctx)
    cells = {}  # (policy, termination) -> summary
    for policy in POLICIES:
        for term in TERMINATIONS:
            rec = newest(evals, policy=policy, termination=term)
            if rec is None and policy == "sft":  # records from before the policy tag existed
                rec = newest([r for r in evals if "policy" not in r.tags], termination=term)
            summary = ctx.report_json(rec, "results.json")
            if summary:
                cells[(policy, term)] = summary
    if not cells:
        return ["No evaluation yet: `python -m stages.evaluate +task=... termination=oracle`."], cells
    cols = [k for k in ((p, t) for t in TERMINATIONS for p in POLICIES) if k in cells]
    rows = []
    for tid, name in sorted({(r["task_id"], r["task"]) for s in cells.values() for r in s["per_task"]}):
        found = [next((r for r in cells[key]["per_task"] if r["task_id"] == tid), None) for key in cols]
        rows.append([f"{tid} {name}", *(f"{100 * r['success_rate']:.0f} %" if r else "" for r in found)])
    rows.append(["**all**", *(f"**{100 * cells[k]['success_rate']:.1f} %**" for k in cols)])
    lines = markdown_table(["task", *(f"{p} / {t}" for p, t in cols)], rows)
    n = {cells[k]["init_states"] for k in cols}
    lines += ["", f"(first {'/'.join(map(str, sorted(n)))} benchmark init states per task)"]
    lines += _paired_lines(ctx, evals)
    for policy in POLICIES:
        refl = cells.get((policy, "reflector"))
        if refl and "reflector_termination" in refl:
            t = refl["reflector_termination"]
            lines += [f"{policy}: reflector `{short_run(refl['reflector'])}` stops in the real simulator (eta {refl['eta']}): "
                      f"termination F1 {t['f1']:.3f}, median timing error {t['timing_error_median']:.0f} steps, "
                      f"{t['false_stops']} false stops, {t['missed_successes']} missed successes."]
    return lines, cells


def _paired_lines(ctx: ReportContext, evals: list[StageRecord]) -> list[str]:
    """SFT vs post-trained on the same episodes, per termination: which episodes only one of them
    solved, and the exact McNemar p-value (is the difference more than chance?)."""
    lines = []
    for term in TERMINATIONS:
        eps = [ctx.report_json(newest(evals, policy=p, termination=term), "episodes.json") for p in POLICIES]
        if not all(eps):
            continue
        sft, post = ({(e["task_id"], e["init_state"]): e["success"] for e in es} for es in eps)
        t = paired_success_test(sft, post)
        if t["episodes"]:
            lines.append(f"{term}, paired over the {t['episodes']} episodes both policies ran: {t['only_a']} solved "
                         f"by SFT only, {t['only_b']} by the post-trained policy only; exact McNemar p = {t['p_value']:.3g}.")
    return [""] + lines if lines else []


def ablation_table(ctx: ReportContext, limit: int = 8) -> list[str]:
    """The paper's Table 2 from what was run: every evaluated policy (SFT and each post-trained
    one, by checkpoint), whether its LOOP's world model saw the extra policy-rollout data, which
    reward it had (the reflector record's `reward` tag), and the imagined reward it optimised;
    each row on the init states it was evaluated on, so only rows with the same count compare."""
    rows: dict[tuple, dict] = {}  # (checkpoint work dir, init states) -> {termination: success}, newest wins
    loops: dict[tuple, StageRecord | None] = {}
    for ev in own_suite_evaluations(ctx):
        summary = ctx.report_json(ev, "results.json")
        loop = ctx.input(ev, "post_train_loop")
        if not summary or (loop is None and ev.tags.get("policy") != "sft"):
            continue
        key = (short_run(summary["policy"]), summary["init_states"])
        rows.setdefault(key, {})[summary["termination"]] = summary["success_rate"]
        loops[key] = loop
    if not any(loops.values()):
        return []
    table = []
    for key in sorted(list(rows)[-limit:], key=lambda k: (k[1], loops[k] is not None)):  # newest `limit`
        loop, cells = loops[key], rows[key]
        data = ctx.input_tags(loop, "train_worldsim").get("data") if loop else None
        extra = {"expert+policy": "yes", "expert": "no (expert demos only)"}.get(data, "")
        reward = f"{ctx.input_tags(loop, 'train_reflector').get('reward', 'trained head')}, eta {loop.tags.get('eta')}" if loop else ""
        table.append([f"{'SFT' if loop is None else 'post-trained'} `{key[0]}`", extra, reward,
                      imagined_span(loop) if loop else "", key[1],
                      *(f"{100 * cells[t]:.1f} %" if t in cells else "" for t in TERMINATIONS)])
    return markdown_table(["policy", "extra data for the world model", "reward", "imagined reward, success (SFT -> last)",
                           "init states per task", *TERMINATIONS], table)


def video_lines(ctx: ReportContext, per_policy: int = 3) -> list[str]:
    """A few episodes of the newest evaluation of each policy under reflector termination (else
    oracle), successes first, copied beside the report so the folder stands on its own."""
    lines = []
    for policy in POLICIES:
        evals = own_suite_evaluations(ctx, policy=policy)
        rec = newest(evals, termination="reflector") or newest(evals, termination="oracle")
        videos = sorted(rec.files("video"), key=lambda a: ("failure" in a.path, a.path)) if rec else []
        for art in videos[:per_policy]:
            copied = ctx.copy(art.path, f"{policy}_{rec.tags['termination']}_{Path(art.path).name}")
            if copied:
                lines.append(f"![{policy}, {rec.tags['termination']} termination: {Path(art.path).stem}]({copied})")
    return lines


def other_suites_table(ctx: ReportContext) -> list[str]:
    """Policies of this task evaluated on another registered suite with the same tasks (`evaluate
    eval_suite=...`, e.g. a LIBERO-PRO perturbation), newest per (policy, suite, termination)."""
    latest = {}
    for r in ctx.find("evaluate"):
        if "eval_suite" in r.tags:
            latest[(r.tags.get("policy"), r.tags["eval_suite"], r.tags["termination"])] = r
    rows = []
    for (policy, suite, term), r in sorted(latest.items(), key=lambda kv: tuple(map(str, kv[0]))):
        summary = ctx.report_json(r, "results.json")
        if summary:
            rows.append([policy, suite, term, summary.get("max_steps", ""), f"{100 * summary['success_rate']:.1f} %",
                         summary["episodes"]])
    return markdown_table(["policy", "evaluated on suite", "termination", "step limit", "success", "episodes"],
                          rows) if rows else []


def view_table(ctx: ReportContext) -> list[str]:
    """`evaluate view_through=...`: each policy's real success when shown the episode as imagination
    would show it (world-model frames, kinematic proprio), paired with its plain evaluation on the
    same episodes: what imagination's view alone costs the policy, before any dynamics."""
    plain = {}
    for r in own_suite_evaluations(ctx):  # newest plain evaluation per (checkpoint, termination)
        summary = ctx.report_json(r, "results.json")
        if summary:
            plain[(summary["policy"], summary["termination"])] = r
    latest = {}
    for r in ctx.find("evaluate"):
        if "view" in r.tags and "eval_suite" not in r.tags:
            latest[(r.config.get("policy_from"), r.metrics.get("view_through"), r.tags["view"], r.tags["termination"])] = r
    rows = []
    for (_, _, parts, term), r in latest.items():
        summary, seen = ctx.report_json(r, "results.json"), ctx.report_json(r, "episodes.json")
        base = plain.get((summary["policy"], term)) if summary else None
        if not base or not seen:
            continue
        a = {(e["task_id"], e["init_state"]): e["success"] for e in ctx.report_json(base, "episodes.json")}
        b = {(e["task_id"], e["init_state"]): e["success"] for e in seen}
        t = paired_success_test(a, b)
        if not t["episodes"]:
            continue
        shared = [k for k in b if k in a]
        rows.append([f"`{checkpoint_name(summary['policy'])}`", parts, f"`{checkpoint_name(r.metrics['view_through'])}`",
                     term, t["episodes"], f"{100 * np.mean([a[k] for k in shared]):.1f} %",
                     f"{100 * np.mean([b[k] for k in shared]):.1f} %", f"{t['only_a']} / {t['only_b']}",
                     f"{t['p_value']:.3g}"])
    return markdown_table(["policy", "shown as imagined", "world model", "termination", "paired episodes", "plain view",
                           "imagination's view", "solved only plain / only imagined view", "McNemar p"],
                          rows) if rows else []


def section(ctx: ReportContext) -> list[str]:
    """evaluate's part of the report: success, other suites, ablations."""
    table, cells = success_table(ctx)
    if cells:
        _plot_success(cells, ctx.out / "success.png")
        table += ["", "![success](success.png)"]
    videos = video_lines(ctx)
    if videos:
        table += ["", "Episodes (first init states of each task; GIFs):", "", *videos]
    return (titled("Success in the real simulator", table)
            + titled(f"Evaluated on other suites (trained on {ctx.task}'s)", other_suites_table(ctx))
            + titled("Shown the real episode as imagination would show it (`evaluate view_through=`)", view_table(ctx))
            + titled("Ablations (the paper's Table 2, as far as run)", ablation_table(ctx)))


def _plot_success(cells: dict, path) -> None:
    keys = [k for k in ((p, t) for t in TERMINATIONS for p in POLICIES) if k in cells]
    tasks = sorted({r["task_id"] for s in cells.values() for r in s["per_task"]})
    fig, ax = figure(figsize=(max(6, len(tasks) * 0.9), 3.2))
    width = 0.8 / len(keys)
    for i, key in enumerate(keys):
        rates = {r["task_id"]: r["success_rate"] for r in cells[key]["per_task"]}
        ax.bar(np.arange(len(tasks)) + i * width, [100 * rates.get(t, 0) for t in tasks], width, label=" / ".join(key))
    ax.set_xticks(np.arange(len(tasks)) + 0.4 - width / 2, [str(t) for t in tasks])
    ax.set_xlabel("task")
    ax.set_ylabel("success %")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    save_figure(fig, path)
