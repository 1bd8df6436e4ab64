"""The cross-suite table: SFT against the post-trained policy on each suite's own experiment
(the paper's Table 1 across suites, and Table 3's terminations), with the paired McNemar test.

    python -m stages.suites outputs/suites libero_goal=outputs/libero_goal-small \
        libero_object=outputs/libero_object-small libero_spatial=outputs/libero_spatial-small

Each experiment's newest evaluations of `sft` and `post_trained` (on its own suite) are read
from its manifest; a suite without them shows as not run. A second table says which limit holds
where post-training does not gain, from the same manifests: the verdict on the SFT policy's paired
replays against issue 22's targets, imagined against real success of the same actions (the world
model's drift), what LOOP raised in imagination, and the real-simulator reference (`env=real`),
which bounds what RL can do at that budget. Writes `<out>/suites.{md,json}`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from stages.evaluate.evaluation import own_suite_evaluations
from stages.evaluate.paired import compare
from stages.evaluate_imagination.evaluation import TARGETS, meets
from worldenv_core.manifest import Manifest
from worldenv_core.report import POLICIES, TERMINATIONS, ReportContext, markdown_table, newest


def suite_row(experiment: str | Path, task: str) -> dict:
    """Per termination: SFT and post-trained success and the paired test over the episodes both ran."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    evals = own_suite_evaluations(ctx)
    row = {"task": task, "experiment": str(experiment)}
    for term in TERMINATIONS:
        found = [newest(evals, policy=p, termination=term) for p in POLICIES]
        episodes = [ctx.report_json(r, "episodes.json") for r in found]
        if not all(episodes):
            continue
        sft, post = ({(e["task_id"], e["init_state"]): bool(e["success"]) for e in es} for es in episodes)
        test = compare(sft, post)
        row[term] = {"sft": test["a"], "post_trained": test["b"],
                     **{k: test[k] for k in ("episodes", "only_a", "only_b", "p_value")}}
    return row


def _first_last(curve: dict | None) -> tuple[float, float] | None:
    """A per-iteration metric ({"0": v, "10": v, ...}) as (first, last), or None if not recorded."""
    points = sorted(((int(k), v) for k, v in (curve or {}).items() if v is not None), key=lambda kv: kv[0])
    return (points[0][1], points[-1][1]) if points else None


def limits(experiment: str | Path, task: str) -> dict:
    """What each limit measured on one suite's experiment, and which of them hold. `verdict`: the
    newest paired-replay run on held-out contexts (its headline policy, normally SFT); `loop`: the
    newest LOOP in imagination; `reference`: the newest LOOP in the real simulator."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    out, holds = {}, []
    fidelity = [r for r in ctx.find("evaluate_imagination") if r.tags.get("contexts", "held_out") == "held_out"]
    if fidelity:
        h = fidelity[-1].metrics.get("headline") or {}
        out["verdict"] = {k: h.get(k) for k in ("auroc", "f1", "hack_rate", "imagined_success", "real_success",
                                                 "rollouts")}
        missed = [k for k in ("auroc", "f1", "hack_rate") if h.get(k) is not None and not meets(k, h[k])]
        if missed:
            holds.append("verdict fidelity (" + ", ".join(missed) + " off target)")
        gap = None if h.get("imagined_success") is None or h.get("real_success") is None else \
            h["imagined_success"] - h["real_success"]
        if gap is not None and abs(gap) > TARGETS["max_task_gap"][1]:
            holds.append(f"world-model drift (imagined - real {100 * gap:+.0f} points)")
    loop = newest(ctx.find("post_train_loop"), env="imagined") or newest(
        [r for r in ctx.find("post_train_loop") if "env" not in r.tags])
    if loop:
        out["loop"] = {k: _first_last(loop.metrics.get(k)) for k in ("imagined_reward", "imagined_success")}
        rise = out["loop"]["imagined_success"]
        if rise and rise[1] <= rise[0]:
            holds.append("no imagined gain to transfer")
    reference = newest(ctx.find("post_train_loop"), env="real")
    if reference:
        out["reference"] = {"real_success": _first_last(reference.metrics.get("real_success"))}
        rise = out["reference"]["real_success"]
        if rise and rise[1] <= rise[0]:
            holds.append("RL capacity (no real gain with the real simulator as environment)")
    out["holds"] = holds
    return out


def _pct(x: float | None) -> str:
    return "" if x is None else f"{100 * x:.1f} %"


def _arrow(pair: tuple[float, float] | None) -> str:
    return "" if not pair else f"{_pct(pair[0])} -> {_pct(pair[1])}"


def limits_table(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        lim = r.get("limits", {})
        v = lim.get("verdict") or {}
        verdict = (f"{v['auroc']:.2f} / {v['f1']:.2f} / {_pct(v['hack_rate'])} ({v['rollouts']})"
                   if v and None not in (v.get("auroc"), v.get("f1"), v.get("hack_rate")) else "not measured")
        same = f"{_pct(v.get('imagined_success'))} / {_pct(v.get('real_success'))}" if v else ""
        loop = lim.get("loop") or {}
        ref = lim.get("reference") or {}
        out.append([r["task"], verdict, same, _arrow(loop.get("imagined_success")),
                    _arrow(ref.get("real_success")) or "not run", "; ".join(lim.get("holds", [])) or "none measured"])
    return markdown_table(["suite", "verdict AUROC / F1 / hack rate (pairs)", "imagined / real success, same actions",
                           "LOOP: imagined success first -> last", "real-simulator reference: real success",
                           "limits that hold"], out)


def table(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        o = r.get("oracle")
        cells = [f"{_pct(o['sft'])} -> {_pct(o['post_trained'])}", f"{100 * (o['post_trained'] - o['sft']):+.1f}",
                 f"{o['only_a']} / {o['only_b']}", f"{o['p_value']:.3g}", o["episodes"]] if o else ["not run", "", "", "", ""]
        for term in ("fixed", "reflector"):
            t = r.get(term)
            cells.append(f"{_pct(t['sft'])} -> {_pct(t['post_trained'])} (p {t['p_value']:.3g})" if t else "")
        out.append([r["task"], *cells])
    return markdown_table(["suite", "oracle: SFT -> post-trained", "gain (points)", "solved only by SFT / post-trained",
                           "McNemar p", "paired episodes", "fixed horizon", "reflector termination"], out)


def write(out: str | Path, experiments: dict[str, str]) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [{**suite_row(exp, task), "limits": limits(exp, task)} for task, exp in experiments.items()]
    (out / "suites.json").write_text(json.dumps(rows, indent=1))
    path = out / "suites.md"
    path.write_text("\n".join(["# SFT against post-trained, per suite", "", *table(rows), "",
                               "## Which limit holds", "",
                               "The verdict is the SFT policy's imagined rollouts judged against their real replays "
                               "(issue 22's targets: AUROC >= 0.90, F1 >= 0.80, hack rate <= 10 %, imagined - real "
                               "within 5 points); the reference is the same LOOP with the real simulator as "
                               "environment (`post_train_loop env=real`).", "", *limits_table(rows)]) + "\n")
    return path


def main(argv: list[str]) -> None:
    if len(argv) < 2 or not all("=" in a for a in argv[1:]):
        raise SystemExit("usage: python -m stages.suites <out_dir> <task>=<experiment_dir> [...]")
    print(write(argv[0], dict(a.split("=", 1) for a in argv[1:])))


if __name__ == "__main__":
    main(sys.argv[1:])
