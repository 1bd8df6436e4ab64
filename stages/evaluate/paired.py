"""Two policies on the real episodes both ran, pooled over evaluation records: success of each,
per task and overall, the episodes only one of them solved, and the exact McNemar p-value.
Several evaluations per side pool their episodes, so a benchmark evaluated in ranges
(`init_states=20`, then `first_init_state=20 init_states=30`) compares as one 500-episode run.
An evaluation is named by its manifest record id or by its output folder (`results.json` and
`episodes.json`, as `evaluate` writes them and as kept under `results/` in the repository).

    python -m stages.evaluate.paired outputs/libero_goal-small \\
        --a evaluate-05f27e1f2f64 evaluate-b3f4f4885ad3 --b evaluate-e20e05a3d33f [--json paired.json]
    python -m stages.evaluate.paired - --a results/libero_goal/evaluate-* --b <work>/evaluate/...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from stages.evaluate.evaluation import checkpoint_name
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import Manifest
from worldenv_core.metrics import paired_difference_ci, paired_success_test
from worldenv_core.report import ReportContext, markdown_table


def read_evaluation(manifest: Manifest | None, name: str) -> tuple[dict | None, list | None]:
    """(results.json, episodes.json) of an evaluation named by output folder or record id."""
    folder = Path(name)
    if (folder / "results.json").is_file():
        rows = folder / "episodes.json"
        return json.loads((folder / "results.json").read_text()), json.loads(rows.read_text()) if rows.is_file() else None
    if manifest is None:
        raise ConfigError(f"{name} is no evaluation folder (results.json, episodes.json), and no experiment "
                          f"directory was given to look it up as a record id")
    rec = manifest.get(name)
    if rec.stage != "evaluate":
        raise ConfigError(f"{name} is a {rec.stage} record, not an evaluation")
    ctx = ReportContext(manifest, "", manifest.root / "report", records=[rec])  # no second read of the manifest
    return ctx.report_json(rec, "results.json", strict=True), ctx.report_json(rec, "episodes.json", strict=True)


def same_policy(first: dict, other: dict) -> bool:
    """One policy when the weights digests agree (a checkpoint copied, released or renamed stays
    itself); evaluations kept before results.json recorded the digest are matched by checkpoint name."""
    if first.get("policy_digest") and other.get("policy_digest"):
        return first["policy_digest"] == other["policy_digest"]
    return checkpoint_name(first["policy"]) == checkpoint_name(other["policy"])


def pooled_episodes(manifest: Manifest | None, names: list[str]) -> tuple[dict[tuple[int, int], bool], dict]:
    """{(task id, init state): success} over the evaluations' episodes (record ids or output
    folders), and their setting (policy, termination, suite): one throughout, and no episode twice
    (which of two runs would count?)."""
    episodes, seen, first = {}, {}, None
    for rid in names:
        summary, rows = read_evaluation(manifest, rid)
        if rows is None or summary is None:
            raise ConfigError(f"{rid}'s episodes.json or results.json is gone")
        first = first or summary
        if not same_policy(first, summary):
            raise ConfigError(f"{rid} evaluated policy {checkpoint_name(summary['policy'])!r}, the evaluations before it "
                              f"{checkpoint_name(first['policy'])!r} (other weights): pool only evaluations of one policy")
        setting = {"termination": summary["termination"], "suite": summary["suite"]}
        for what, value in setting.items():
            if seen.setdefault(what, value) != value:
                raise ConfigError(f"{rid} evaluated {what} {value!r}, the evaluations before it "
                                  f"{seen[what]!r}: pool only evaluations of one policy and setting")
        for r in rows:
            key = (r["task_id"], r["init_state"])
            if key in episodes:
                raise ConfigError(f"task {key[0]} init state {key[1]} is in {rid} and in an evaluation before it")
            episodes[key] = bool(r["success"])
    return episodes, {**seen, "policy": checkpoint_name(first["policy"])}


def pooled_policies(manifest: Manifest | None, groups: list[list[str]]) -> list[tuple[dict, dict]]:
    """`pooled_episodes` of each group of evaluations (one policy each), refused unless all ran the
    same termination on the same suite (else they are not the same episodes)."""
    sides = [pooled_episodes(manifest, names) for names in groups]
    for what in ("termination", "suite"):
        if len({setting[what] for _, setting in sides}) > 1:
            raise ConfigError(f"the policies ran different {what}s ({sorted({s[what] for _, s in sides})}): "
                              "not the same episodes")
    return sides


def emit(result: dict, table: str, json_path: str | None = None, draw=None, plot_path: str | None = None) -> dict:
    """The end every comparison command shares: print its table, write its result as JSON and
    draw its figure where asked (`draw(result, path)`). -> the result."""
    print(table, end="")
    if json_path:
        write_text_atomic(json_path, json.dumps(result, indent=1))
    if plot_path and draw is not None:
        draw(result, plot_path)
    return result


def paired_gain(base: dict, other: dict, keys: list) -> dict:
    """`other`'s success minus `base`'s on `keys`, with its 95 % paired interval, the discordant counts and
    the exact McNemar p."""
    test = paired_success_test({k: base[k] for k in keys}, {k: other[k] for k in keys})
    return {"gain": (test["only_b"] - test["only_a"]) / len(keys),
            "ci": paired_difference_ci(test["only_a"], test["only_b"], len(keys)),
            "only_first": test["only_a"], "only_second": test["only_b"], "p_value": test["p_value"]}


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


def markdown(result: dict, a: str = "a", b: str = "b") -> str:
    rows = [[t["task_id"], t["n"], f"{100 * t['a']:.0f} %", f"{100 * t['b']:.0f} %", f"{t['only_a']} / {t['only_b']}"]
            for t in result["per_task"]]
    rows.append(["**all**", result["episodes"], f"**{100 * result['a']:.1f} %**", f"**{100 * result['b']:.1f} %**",
                 f"{result['only_a']} / {result['only_b']}"])
    return "\n".join([*markdown_table(["task", "episodes", a, b, "solved only by the first / only by the second"], rows), "",
                      f"exact McNemar p = {result['p_value']:.3g} over {result['episodes']} paired episodes"]) + "\n"


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--a", nargs="+", required=True, help="evaluations of the first policy (pooled)")
    p.add_argument("--b", nargs="+", required=True, help="evaluations of the second policy (pooled)")
    p.add_argument("--json", help="also write the result here")
    args = p.parse_args(argv)
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    (a, a_setting), (b, b_setting) = pooled_episodes(manifest, args.a), pooled_episodes(manifest, args.b)
    for what in ("termination", "suite"):
        if a_setting[what] != b_setting[what]:
            raise ConfigError(f"the sides ran {what} {a_setting[what]!r} and {b_setting[what]!r}: not the same episodes")
    result = compare(a, b)
    result.update(a_records=args.a, b_records=args.b, a_policy=a_setting["policy"], b_policy=b_setting["policy"],
                  termination=a_setting["termination"], suite=a_setting["suite"])
    return emit(result, markdown(result, a_setting["policy"], b_setting["policy"]), args.json)


if __name__ == "__main__":
    main()
