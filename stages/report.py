"""The experiment report, `<experiment>/report/report.md`, rebuilt from the manifest after every
evaluation: the sum of the stages' sections in pipeline order (each stage's
`evaluation.section(ctx)`), then the wall time of each stage's newest run.

    python -m stages.report outputs/libero_goal-small libero_goal
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from stages.collect import evaluation as collect
from stages.evaluate import evaluation as evaluate
from stages.evaluate_imagination import evaluation as evaluate_imagination
from stages.post_train_loop import evaluation as post_train_loop
from stages.train_reflector import evaluation as train_reflector
from stages.train_worldsim import evaluation as train_worldsim
from worldenv_core.files import write_text_atomic
from worldenv_core.locks import waiting_lock
from worldenv_core.manifest import Manifest, StageRecord
from worldenv_core.report import ReportContext, markdown_table, titled

# Results first (what a reader came for), then how the parts that produced them did.
SECTIONS = (evaluate.section, evaluate_imagination.section, post_train_loop.section, train_worldsim.section,
            train_reflector.section, collect.section)


def write_report(experiment_dir: str | Path, task: str) -> Path:
    out = Path(experiment_dir) / "report"
    with waiting_lock(out / ".lock"):  # runs finishing together: each rebuilds from the manifest as it is then
        ctx = ReportContext(Manifest(experiment_dir), task, out)
        lines = [f"# {task}: experiment report"]
        for section in SECTIONS:
            lines += section(ctx)
        lines += real_episodes_section(ctx)
        lines += wall_time_section(ctx)
        return write_text_atomic(ctx.out / "report.md", "\n".join(lines) + "\n")


def _producer(record: StageRecord, records: list[StageRecord]) -> StageRecord:
    """The first record of the same stage whose outputs hold this one's trained weights or episodes
    (by content): the run that did the work a later re-run found finished."""
    made = {a.sha256 for a in record.outputs  # the weights, not config.json: its metadata names the run
            if a.kind == "episodes" or (a.kind == "checkpoint" and a.path.endswith(".safetensors"))}
    return next((r for r in records if made and r.stage == record.stage
                 and made <= {a.sha256 for a in r.outputs}), record)


def _latest_by_tags(ctx: ReportContext) -> list[StageRecord]:
    """The newest record of each stage and tag set of this task: the pipeline as it stands."""
    latest = {}
    for r in ctx.records:
        if r.tags.get("task") == ctx.task:
            latest[(r.stage, json.dumps(r.tags, sort_keys=True))] = r
    return list(latest.values())


# What a stage's real-simulator episodes are for; post_train_loop's only monitor (never train).
PURPOSE = {"collect": "training data", "evaluate": "evaluation", "evaluate_imagination": "evaluation (paired replay)",
           "post_train_loop": "evaluation (monitoring during training)"}


def real_episodes_section(ctx: ReportContext) -> list[str]:
    """Real-simulator episodes, the resource the method exists to save, per stage run (newest of
    each tag set) and in total; every attempt counts, failed expert attempts included."""
    rows, totals = [], {}
    for r in _latest_by_tags(ctx):
        if r.stage not in PURPOSE:
            continue
        n = r.metrics.get("real_episodes")
        labelling = r.stage == "evaluate_imagination" and r.tags.get("contexts") == "training"
        purpose = ("training data: real outcomes labelling imagined rollouts for a reflector" if labelling
                   else PURPOSE[r.stage] + (f": {r.tags['source']}" if r.stage == "collect" else ""))
        rows.append([r.stage, ", ".join(f"{k}={v}" for k, v in r.tags.items() if k not in ("task", "worldsim", "reflector")),
                     purpose, "not recorded" if n is None else n])
        if n is not None:
            key = "training data" if r.stage == "collect" or labelling else "evaluation"
            totals[key] = totals.get(key, 0) + n
        if r.metrics.get("train_real_episodes"):  # post_train_loop env=real: the reference trains on them
            rows.append([r.stage, rows[-1][1], "training rollouts (the real-simulator reference)",
                         r.metrics["train_real_episodes"]])
            totals["training data"] = totals.get("training data", 0) + r.metrics["train_real_episodes"]
    if not rows:
        return []
    total = ", ".join(f"{k}: {v}" for k, v in sorted(totals.items(), reverse=True))
    return titled("Real-simulator episodes", [
        "Each stage's newest run; an episode is one reset of the real simulator (expert attempts that failed count, "
        "and a paired replay or a closed-loop rollout counts one). The world model, the reflector (also when trained "
        "on imagined replays: their labels are the recorded episodes' own) and post-training's updates use none.", "",
        *markdown_table(["stage", "tags", "for", "real episodes"], rows), "", f"Total: {total}."])


def wall_time_section(ctx: ReportContext) -> list[str]:
    rows, runs = [], {}
    for r in _latest_by_tags(ctx):
        made = _producer(r, ctx.records)
        rows.append([r.stage, ", ".join(f"{k}={v}" for k, v in r.tags.items() if k != "task"), f"`{made.id}`",
                     f"{made.wall_time_s:.0f}"])
        # one evaluation pass writes a record per termination mode, all with its config and start
        runs[(made.stage, made.config_hash, made.started)] = made.wall_time_s
    total = sum(runs.values())
    return titled("Wall time per stage", [
        "Newest run of each; a re-run that found the work done is timed by the run that produced its files "
        "(its last sitting, if it was resumed).", "", *markdown_table(["stage", "tags", "record", "wall s"], rows), "",
        f"Total: {total:.0f} s ({int(total // 3600)} h {int(total % 3600 // 60):02d} min), the records of one "
        "evaluation pass (`termination=all`) counted once."])


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python -m stages.report <experiment_dir> <task>")
    print(write_report(sys.argv[1], sys.argv[2]))
