"""Kept evaluations, read, pooled and paired: what every comparison of two policies on the real
benchmark starts from. An evaluation is named by its manifest record id or by its output folder
(`results.json` and `episodes.json`, as `evaluate` writes them and as kept under `results/` in the
repository); several evaluations of one policy pool their episodes, so a benchmark evaluated in
ranges compares as one 500-episode run; two policies are compared on the episodes both ran, with
the exact McNemar test (`worldenv_core.stats`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import Manifest
from worldenv_core.report import ReportContext, markdown_table, short_run
from worldenv_core.stats import paired_difference_ci, paired_success_test


def checkpoint_name(path: str) -> str:
    """A stage run's checkpoint by <stage>/<work dir>, any other folder (released under checkpoints/,
    refitted, copied) by its parent and name."""
    parts = Path(path).parts
    work = parts[-2] if len(parts) >= 2 else ""
    return short_run(path) if len(work) == 16 and all(c in "0123456789abcdef" for c in work) else "/".join(parts[-2:])


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


def paired_markdown(result: dict, a: str = "a", b: str = "b") -> str:
    """`compare`'s result as a per-task table with the exact McNemar p under it."""
    rows = [[t["task_id"], t["n"], f"{100 * t['a']:.0f} %", f"{100 * t['b']:.0f} %", f"{t['only_a']} / {t['only_b']}"]
            for t in result["per_task"]]
    rows.append(["**all**", result["episodes"], f"**{100 * result['a']:.1f} %**", f"**{100 * result['b']:.1f} %**",
                 f"{result['only_a']} / {result['only_b']}"])
    return "\n".join([*markdown_table(["task", "episodes", a, b, "solved only by the first / only by the second"], rows), "",
                      f"exact McNemar p = {result['p_value']:.3g} over {result['episodes']} paired episodes"]) + "\n"
