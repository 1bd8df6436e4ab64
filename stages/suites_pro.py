"""The perturbed-suite table (LIBERO-PRO's perturbations the benchmark registers for a suite:
`<suite>_swap`, `_lan`, `_object`, `_task`): each released SFT and post-trained policy evaluated there
(`evaluate eval_suite=...`, the source suite's step limit), paired by episode, beside its own suite.
Writes `<out>/suites_pro.{md,json}`.

From experiments (`make suites-pro` runs the evaluations into outputs/release-<suite>, LeRobot's ACT
into outputs/release-<suite>-act and the true-reward ES policy into outputs/release-<suite>-es): each
side's newest oracle evaluation per evaluated suite. A key `<task>:<label>` names another release of the
same suite, shown by its label; a release post-trained from another's SFT (SFT_OF) is paired with that
SFT's evaluations.

    python -m stages.suites_pro results/suites-pro libero_spatial=outputs/release-libero_spatial \\
        libero_spatial:ACT=outputs/release-libero_spatial-act libero_spatial:ES=outputs/release-libero_spatial-es

From the evaluations kept in the repository (`results/<suite>/evaluate-*`, `analysis.keep`; no
simulator, seconds; `make suites-pro-table`): every kept oracle evaluation on a perturbed suite of a
released checkpoint (`checkpoints/<suite>/<folder>`, RELEASES below), pooled per side; a side with none
reads "not run" if its checkpoint has a kept evaluation elsewhere, else "not released".

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
            "act_sft": ("ACT", "sft"), "act_post_trained": ("ACT", "post_trained"),
            "es_post_trained": ("ES", "post_trained")}
# releases post-trained from another release's SFT, paired with that SFT's evaluations (ES: the project's SFT moved
# by the real route's ES with the true reward, `make es-post-trained`)
SFT_OF = {"ES": PROJECT_RELEASE}


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


def _newest_oracle(experiment: str | Path, task: str) -> dict[str, dict]:
    """evaluated suite ("own suite" for the task's own) -> policy -> (its experiment's report context, its
    newest oracle evaluation record)."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    found: dict[str, dict] = {}
    for r in ctx.find("evaluate", termination="oracle"):
        if not {"view", "first_init_state"} & set(r.tags) and r.tags.get("policy") in POLICIES:
            found.setdefault(r.tags.get("eval_suite") or "own suite", {})[r.tags["policy"]] = (ctx, r)
    return found


def perturbed_rows(experiment: str | Path, task: str, release: str = PROJECT_RELEASE,
                   sft_from: str | Path | None = None) -> list[dict]:
    """One row per suite the task's policies were evaluated on with oracle termination, its own
    first: each side's success on its newest evaluation there, and the paired test where both ran.
    release: which policies these are (the project's, or e.g. "ACT"), a column of the table; sft_from:
    the experiment whose SFT evaluations stand for this release's SFT side (SFT_OF)."""
    found = _newest_oracle(experiment, task)
    for suite, sides in (_newest_oracle(sft_from, task) if sft_from is not None else {}).items():
        if suite in found and "sft" in sides:
            found[suite].setdefault("sft", sides["sft"])
    rows = []
    for suite in sorted(found, key=lambda k: (k != "own suite", k)):
        sides = {p: ctx.report_json(r, "episodes.json") for p, (ctx, r) in found[suite].items()}
        outcomes = {p: {(e["task_id"], e["init_state"]): bool(e["success"]) for e in es} for p, es in sides.items() if es}
        ctx, record = next(iter(found[suite].values()))
        summary = ctx.report_json(record, "results.json") or {}
        own = suite == "own suite"
        rows.append(_row(task, release, summary.get("suite", task) if own else suite, own, summary.get("max_steps"),
                         outcomes))
    return rows


def kept_perturbed_rows(folder: str | Path, task: str) -> list[dict]:
    """Rows from the kept evaluations under `folder` (results/<task>): per release, per perturbed suite,
    each side's kept oracle evaluations of its released checkpoint, pooled (no episode twice)."""
    groups: dict[tuple[str, str], dict[str, list[str]]] = {}  # (release, suite) -> side -> folders
    steps: dict[str, int] = {}
    evaluated: set[tuple[str, str]] = set()  # (release, side) with a kept evaluation on any suite
    for results in sorted(Path(folder).glob("evaluate-*/results.json")):
        summary = json.loads(results.read_text())
        suite, policy = summary.get("suite", ""), Path(summary.get("policy", ""))
        released = policy.parent == Path("checkpoints") / task and policy.name in RELEASES
        if released:
            evaluated.add(RELEASES[policy.name])
        if summary.get("termination") == "oracle" and suite.startswith(f"{task}_") and released:
            release, side = RELEASES[policy.name]
            groups.setdefault((release, suite), {}).setdefault(side, []).append(str(results.parent))
            steps[suite] = summary.get("max_steps")
    order = list(dict.fromkeys(r for r, _ in RELEASES.values()))
    rows = []
    for release, suite in sorted(groups, key=lambda k: (order.index(k[0]), k[1])):
        sides = dict(groups[(release, suite)])
        base = groups.get((SFT_OF.get(release), suite), {})
        if "sft" in base:
            sides.setdefault("sft", base["sft"])
        outcomes = {side: pooled_episodes(None, names)[0] for side, names in sides.items()}
        # a post-trained side missing here is "not run" where it was evaluated anywhere (its own suite's 500 are
        # kept for every release), else "not released" (libero_goal's post-training gained nothing, so none was)
        missing = "not run" if (release, "post_trained") in evaluated else "not released"
        rows.append({**_row(task, release, suite, False, steps[suite], outcomes), "missing": missing})
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
        rows = []
        for key, exp in sources.items():
            task, _, label = key.partition(":")
            of = SFT_OF.get(label)  # the release whose SFT side this one shares, keyed as the sources are
            base = None if of is None else sources.get(task if of == PROJECT_RELEASE else f"{task}:{of}")
            rows += perturbed_rows(exp, task, label or PROJECT_RELEASE, sft_from=base)
        made = "`make suites-pro`"
    write_text_atomic(out / "suites_pro.json", json.dumps(rows, indent=1))
    path = out / "suites_pro.md"
    write_text_atomic(path, "\n".join([
        "# Released policies on the perturbed suites (LIBERO-PRO)", "",
        "Each released policy on the perturbed suites the benchmark registers for its suite "
        "(`_swap`: objects' positions swapped, `_lan`: the instruction reworded, `_object`: objects replaced, "
        "`_task`: a new task in the scene), oracle termination with the source suite's step limit, SFT and "
        f"post-trained paired by (task, init state) with the exact McNemar test. Generated by {made}.", "",
        "Policies: the project's releases (`checkpoints/<suite>/sft`, `post_trained`: LOOP in imagination); ACT, "
        "LeRobot's (`act_sft`, `act_post_trained`: the real route's ES); ES, the project's SFT post-trained by the "
        "real route's ES with the true reward (`es_post_trained`, `make es-post-trained`), paired with the project's "
        "SFT. \"not released\": that suite's post-training gained nothing and was not released.", "",
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
