"""The cross-suite table: SFT against the post-trained policy on each suite's own experiment
(the paper's Table 1 across suites, and Table 3's terminations), with the paired McNemar test.

    python -m stages.suites outputs/suites libero_goal=outputs/libero_goal-small \
        libero_object=outputs/libero_object-small libero_spatial=outputs/libero_spatial-small

Each experiment's newest evaluations of `sft` and `post_trained` (on its own suite) are read
from its manifest; a suite without them shows as not run. Writes `<out>/suites.{md,json}`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from stages.evaluate.evaluation import own_suite_evaluations
from stages.evaluate.paired import compare
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


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


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
    rows = [suite_row(exp, task) for task, exp in experiments.items()]
    (out / "suites.json").write_text(json.dumps(rows, indent=1))
    path = out / "suites.md"
    path.write_text("\n".join(["# SFT against post-trained, per suite", "", *table(rows)]) + "\n")
    return path


def main(argv: list[str]) -> None:
    if len(argv) < 2 or not all("=" in a for a in argv[1:]):
        raise SystemExit("usage: python -m stages.suites <out_dir> <task>=<experiment_dir> [...]")
    print(write(argv[0], dict(a.split("=", 1) for a in argv[1:])))


if __name__ == "__main__":
    main(sys.argv[1:])
