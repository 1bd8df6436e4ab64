"""How well did an ES run measure its directions? Its ledgers read within tasks, across tasks and under discounts.

Each ledger entry keeps every member's outcome and steps from every start of its iteration, so how repeatable the
pair differences were can be judged after the fact, without a real episode (`es.half_agreement`):

* within tasks: each task's starts split in two halves; the cosine of the pair differences on one half with those on
  the other (about 0: the starts' noise; toward 1: the directions carry a signal the step can follow);
* across tasks: the tasks at even positions against those at odd ones: does a direction that helps some tasks help
  the others? About 0 or below says a step chosen on some tasks is a random move for the rest;
* under a discount (`rl.es_discount` < 1, a faster success worth more), judged by success on the other half: would a
  shaped return have measured the success direction better than success itself?

Contexts numbered as fresh placements are of task number mod the suite's task count (`--tasks`, 10 for LIBERO's
suites); a run on one task (`task.task_ids=[4]`) is named with `:1` after its folder.

    python -m analysis.ledger_agreement results/rl_recipes/es_task4_seed0_ledger:1 \\
        results/rl_recipes/es_by_task_seed0_ledger results/rl_recipes/es_every_task_seed0_ledger \\
        --json results/rl_recipes/ledger_agreement.json --markdown results/rl_recipes/ledger_agreement.md
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def table(ledgers: dict[str, tuple[list[dict], int]], discounts: list[float]) -> list[dict]:
    """One row per (ledger, discount): iterations, tasks, the within-task agreement, the agreement across tasks
    (null for one task's run or a run whose iterations each held one task) and the within-task agreement judged by
    success."""
    from worldenv_core.rl.es import half_agreement

    rows = []
    for name, (entries, n_tasks) in ledgers.items():
        for d in discounts:
            across = half_agreement(entries, d, n_tasks=n_tasks, across_tasks=True)["pooled"] if n_tasks > 1 else None
            rows.append({"ledger": name, "iterations": len(entries), "tasks": n_tasks, "discount": d,
                         "within_tasks": half_agreement(entries, d, n_tasks=n_tasks)["pooled"],
                         "across_tasks": None if across is None or math.isnan(across) else across,
                         "judged_by_success": half_agreement(entries, d, judged_by=1.0, n_tasks=n_tasks)["pooled"]})
    return rows


def markdown(rows: list[dict]) -> str:
    def f(x):
        return "-" if x is None else f"{x:.2f}"
    out = ["| ledger | iterations | discount | within tasks | across tasks | within, judged by success |",
           "| --- | --- | --- | --- | --- | --- |"]
    out += [f"| {r['ledger']} | {r['iterations']} | {r['discount']:g} | {f(r['within_tasks'])} | "
            f"{f(r['across_tasks'])} | {f(r['judged_by_success'])} |" for r in rows]
    return "\n".join(out) + "\n"


def parse_ledger(arg: str, default_tasks: int) -> tuple[Path, int]:
    """FOLDER or FOLDER:N (its run's task count)."""
    head, _, n = arg.rpartition(":")
    folder, n_tasks = (head, int(n)) if head and n.isdigit() else (arg, default_tasks)
    if n_tasks < 1:
        raise ConfigError(f"{arg}: a run has at least one task")
    return Path(folder), n_tasks


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ledgers", nargs="+", help="ES ledger folders (iter_NNNN.json), each FOLDER or FOLDER:TASKS")
    ap.add_argument("--tasks", type=int, default=10, help="the runs' task count where a folder names none")
    ap.add_argument("--discounts", nargs="+", type=float, default=[1.0, 0.99, 0.97, 0.95])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--markdown", type=Path, help="write the table here")
    args = ap.parse_args(argv)
    with user_errors():
        from worldenv_core.rl.es import read_ledger

        bad = [d for d in args.discounts if not 0 < d <= 1]
        if bad:
            raise ConfigError(f"--discounts must lie in (0, 1], got {bad}")
        ledgers = {}
        for arg in args.ledgers:
            folder, n_tasks = parse_ledger(arg, args.tasks)
            entries = read_ledger(folder)
            if not entries:
                raise ConfigError(f"{folder}: no iter_NNNN.json (not an ES ledger)")
            ledgers[folder.name.removesuffix("_ledger")] = entries, n_tasks
        rows = table(ledgers, args.discounts)
        text = markdown(rows)
        print(text, end="")
        if args.json:
            write_text_atomic(args.json, json.dumps(rows, indent=1))
        if args.markdown:
            write_text_atomic(args.markdown, text)
        return rows


if __name__ == "__main__":
    main()
