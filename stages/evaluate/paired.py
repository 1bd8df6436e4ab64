"""Two policies on the real episodes both ran, pooled over evaluation records: success of each,
per task and overall, the episodes only one of them solved, and the exact McNemar p-value.
Several records per side pool their episodes, so a benchmark evaluated in ranges
(`init_states=20`, then `first_init_state=20 init_states=30`) compares as one 500-episode run.

    python -m stages.evaluate.paired outputs/libero_goal-small \\
        --a evaluate-05f27e1f2f64 evaluate-b3f4f4885ad3 --b evaluate-e20e05a3d33f [--json paired.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.metrics import paired_success_test
from worldenv_core.report import ReportContext, markdown_table


def pooled_episodes(manifest: Manifest, record_ids: list[str]) -> dict[tuple[int, int], bool]:
    """{(task id, init state): success} over the records' episodes; one termination mode and one
    policy checkpoint throughout, and no episode twice (which of two runs would count?)."""
    ctx = ReportContext(manifest, "", manifest.root / "report")
    episodes, seen = {}, {}
    for rid in record_ids:
        rec = manifest.get(rid)
        if rec.stage != "evaluate":
            raise ConfigError(f"{rid} is a {rec.stage} record, not an evaluation")
        rows, summary = ctx.report_json(rec, "episodes.json"), ctx.report_json(rec, "results.json")
        if rows is None or summary is None:
            raise ConfigError(f"{rid}'s episodes.json or results.json is gone from {manifest.root}")
        for what in ("termination", "policy", "suite"):
            if seen.setdefault(what, summary[what]) != summary[what]:
                raise ConfigError(f"{rid} evaluated {what} {summary[what]!r}, the records before it "
                                  f"{seen[what]!r}: pool only evaluations of one policy and setting")
        for r in rows:
            key = (r["task_id"], r["init_state"])
            if key in episodes:
                raise ConfigError(f"task {key[0]} init state {key[1]} is in {rid} and in a record before it")
            episodes[key] = bool(r["success"])
    return episodes


def compare(a: dict, b: dict) -> dict:
    """The paired test over the episodes both ran, with each side's success on exactly those."""
    keys = sorted(set(a) & set(b))
    if not keys:
        raise ConfigError("the two sides share no episode (task, init state)")
    per_task = []
    for tid in sorted({t for t, _ in keys}):
        ks = [k for k in keys if k[0] == tid]
        per_task.append({"task_id": tid, "n": len(ks), "a": float(np.mean([a[k] for k in ks])),
                         "b": float(np.mean([b[k] for k in ks])), **paired_success_test(
                             {k: a[k] for k in ks}, {k: b[k] for k in ks})})
    return {"a": float(np.mean([a[k] for k in keys])), "b": float(np.mean([b[k] for k in keys])),
            **paired_success_test(a, b), "per_task": per_task}


def markdown(result: dict) -> str:
    rows = [[t["task_id"], t["n"], f"{100 * t['a']:.0f} %", f"{100 * t['b']:.0f} %", f"{t['only_a']} / {t['only_b']}"]
            for t in result["per_task"]]
    rows.append(["**all**", result["episodes"], f"**{100 * result['a']:.1f} %**", f"**{100 * result['b']:.1f} %**",
                 f"{result['only_a']} / {result['only_b']}"])
    return "\n".join([*markdown_table(["task", "episodes", "a", "b", "solved only by a / only by b"], rows), "",
                      f"exact McNemar p = {result['p_value']:.4f} over {result['episodes']} paired episodes"]) + "\n"


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir")
    p.add_argument("--a", nargs="+", required=True, help="evaluate record ids of the first policy (pooled)")
    p.add_argument("--b", nargs="+", required=True, help="evaluate record ids of the second policy (pooled)")
    p.add_argument("--json", help="also write the result here")
    args = p.parse_args(argv)
    manifest = Manifest(args.experiment_dir)
    result = compare(pooled_episodes(manifest, args.a), pooled_episodes(manifest, args.b))
    result.update(a_records=args.a, b_records=args.b)
    print(markdown(result), end="")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
