"""The perturbed-suite table (LIBERO-PRO's perturbations the benchmark registers for a suite:
`<suite>_swap`, `_lan`, `_object`, `_task`): each released SFT and post-trained policy evaluated there
(`evaluate eval_suite=...`, the source suite's step limit), paired by episode, beside its own suite.
Writes `<out>/suites_pro.{md,json}`.

From experiments (`make suites-pro` runs the evaluations into outputs/release-<suite>, and LeRobot's
ACT into outputs/release-<suite>-act): each side's newest oracle evaluation per evaluated suite. A key
`<task>:<label>` names another release of the same suite, shown by its label.

    python -m stages.suites_pro results/suites-pro libero_spatial=outputs/release-libero_spatial \\
        libero_spatial:ACT=outputs/release-libero_spatial-act

From the evaluations kept in the repository (`results/<suite>/evaluate-*`, `analysis.keep`; no
simulator, seconds; `make suites-pro-table`): every kept oracle evaluation on a perturbed suite of a
released checkpoint (`checkpoints/<suite>/<folder>`, RELEASES below), pooled per side.

    python -m stages.suites_pro --kept results/suites-pro libero_spatial=results/libero_spatial
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from stages.suites import _paired, _pct
from worldenv_core.cli import user_errors
from worldenv_core.evaluations import pooled_episodes
from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import Manifest
from worldenv_core.report import POLICIES, ReportContext, markdown_table

PROJECT_RELEASE = "the project's"  # the releases' column where a key names no other (`<task>:<label>`)
# released checkpoint folder (checkpoints/<suite>/<folder>) -> (release, side)
RELEASES = {"sft": (PROJECT_RELEASE, "sft"), "post_trained": (PROJECT_RELEASE, "post_trained"),
            "act_sft": ("ACT", "sft"), "act_post_trained": ("ACT", "post_trained")}


def _row(task: str, release: str, suite: str, own: bool, max_steps, outcomes: dict) -> dict:
    """A table row from each side's {(task id, init state): success} on one evaluated suite (own: the
    source suite itself)."""
    row = {"task": task, "release": release, "suite": suite, "perturbation": "none" if own else suite.rsplit("_", 1)[-1],
           "max_steps": max_steps,
           **{p: sum(o.values()) / len(o) for p, o in outcomes.items() if o},
           **{f"{p}_episodes": len(o) for p, o in outcomes.items()}}
    if all(p in outcomes for p in POLICIES):
        row["paired"] = _paired(outcomes["sft"], outcomes["post_trained"])
    return row


def perturbed_rows(experiment: str | Path, task: str, release: str = PROJECT_RELEASE) -> list[dict]:
    """One row per suite the task's policies were evaluated on with oracle termination, its own
    first: each side's success on its newest evaluation there, and the paired test where both ran.
    release: which policies these are (the project's, or e.g. "ACT"), a column of the table."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    found: dict[str, dict] = {}  # evaluated suite -> policy -> newest record
    for r in ctx.find("evaluate", termination="oracle"):
        if not {"view", "first_init_state"} & set(r.tags) and r.tags.get("policy") in POLICIES:
            suite = r.tags.get("eval_suite") or "own suite"
            found.setdefault(suite, {})[r.tags["policy"]] = r
    rows = []
    for suite in sorted(found, key=lambda k: (k != "own suite", k)):
        sides = {p: ctx.report_json(r, "episodes.json") for p, r in found[suite].items()}
        outcomes = {p: {(e["task_id"], e["init_state"]): bool(e["success"]) for e in es} for p, es in sides.items() if es}
        summary = ctx.report_json(next(iter(found[suite].values())), "results.json") or {}
        own = suite == "own suite"
        rows.append(_row(task, release, summary.get("suite", task) if own else suite, own, summary.get("max_steps"),
                         outcomes))
    return rows


def kept_perturbed_rows(folder: str | Path, task: str) -> list[dict]:
    """Rows from the kept evaluations under `folder` (results/<task>): per release, per perturbed suite,
    each side's kept oracle evaluations of its released checkpoint, pooled (no episode twice)."""
    groups: dict[tuple[str, str], dict[str, list[str]]] = {}  # (release, suite) -> side -> folders
    steps: dict[str, int] = {}
    for results in sorted(Path(folder).glob("evaluate-*/results.json")):
        summary = json.loads(results.read_text())
        suite, policy = summary.get("suite", ""), Path(summary.get("policy", ""))
        released = policy.parent == Path("checkpoints") / task and policy.name in RELEASES
        if summary.get("termination") == "oracle" and suite.startswith(f"{task}_") and released:
            release, side = RELEASES[policy.name]
            groups.setdefault((release, suite), {}).setdefault(side, []).append(str(results.parent))
            steps[suite] = summary.get("max_steps")
    order = list(dict.fromkeys(r for r, _ in RELEASES.values()))
    rows = []
    for release, suite in sorted(groups, key=lambda k: (order.index(k[0]), k[1])):
        outcomes = {side: pooled_episodes(None, names)[0] for side, names in groups[(release, suite)].items()}
        # a side with no kept evaluation is one not run yet (its release's other side is kept, so it is released)
        rows.append({**_row(task, release, suite, False, steps[suite], outcomes), "missing": "not run"})
    return rows


def perturbed_table(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        t = r.get("paired")
        out.append([r["task"], r.get("release", PROJECT_RELEASE), r["suite"], r["perturbation"], r.get("max_steps") or "",
                    f"{_pct(r.get('sft'))} ({r.get('sft_episodes', 0)})" if "sft" in r else "not run",
                    f"{_pct(r.get('post_trained'))} ({r.get('post_trained_episodes', 0)})" if "post_trained" in r
                    else r.get("missing", "not released"),
                    f"{100 * (t['post_trained'] - t['sft']):+.1f}" if t else "", f"{t['only_a']} / {t['only_b']}" if t else "",
                    format(t["p_value"], ".3g") if t else ""])
    return markdown_table(["source suite", "policies", "evaluated on", "perturbation", "step limit", "SFT (episodes)",
                           "post-trained (episodes)", "gain (points)", "solved only by SFT / post-trained",
                           "McNemar p"], out)


def write_perturbed(out: str | Path, sources: dict[str, str], kept: bool = False) -> Path:
    """sources: `<task>[:<label>]` -> experiment directory, or (kept) `<task>` -> its kept evaluations' folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if kept:
        rows = [row for task, folder in sources.items() for row in kept_perturbed_rows(folder, task)]
        made = f"`python -m stages.suites_pro --kept` (`make suites-pro-table`) from the evaluations kept under `results/`"
    else:
        rows = [row for key, exp in sources.items() for row in perturbed_rows(exp, *key.split(":", 1))]
        made = "`make suites-pro`"
    write_text_atomic(out / "suites_pro.json", json.dumps(rows, indent=1))
    path = out / "suites_pro.md"
    write_text_atomic(path, "\n".join([
        "# Released policies on the perturbed suites (LIBERO-PRO)", "",
        "Each released policy on the perturbed suites the benchmark registers for its suite "
        "(`_swap`: objects' positions swapped, `_lan`: the instruction reworded, `_object`: objects replaced, "
        "`_task`: a new task in the scene), oracle termination with the source suite's step limit, SFT and "
        f"post-trained paired by (task, init state) with the exact McNemar test. Generated by {made}.", "",
        *perturbed_table(rows)]) + "\n")
    return path


USAGE = ("usage: python -m stages.suites_pro <out_dir> <task>[:<label>]=<experiment_dir> [...]\n"
         "       python -m stages.suites_pro --kept <out_dir> <task>=<kept evaluations' folder> [...]")


def main(argv: list[str]) -> None:
    kept = argv[:1] == ["--kept"]
    args = argv[1:] if kept else argv
    if len(args) < 2 or not all("=" in a for a in args[1:]):
        raise SystemExit(USAGE)
    print(write_perturbed(args[0], dict(a.split("=", 1) for a in args[1:]), kept=kept))


if __name__ == "__main__":
    with user_errors():
        main(sys.argv[1:])
