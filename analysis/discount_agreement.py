"""Would a shaped return have measured an ES run's directions better? Its ledgers, re-read under discounts.

An ES member's return is its success rate over the iteration's starts (`rl.es_discount` 1: the benchmark's
measure). With a discount < 1 a faster success is worth more, a graded signal among successes that a 0/1
outcome lacks. Each ledger keeps every member's outcome and steps from every start, so any discount can be
judged after the fact, without a real episode: for each discount, the even/odd-start agreement of the pair
differences (`es.half_agreement`: does the measured direction repeat on other starts?) and the same judged
by success on the other half (`judged_by=1`: does it point where the benchmark's success does?). A discount
whose second figure beats success's own agreement measures the success direction better than success does.

    python -m analysis.discount_agreement results/rl_recipes/es_by_task_seed0_ledger \\
        results/rl_recipes/es_suite_seed0_ledger --discounts 1 0.99 0.98 0.97 0.95 \\
        --json results/rl_recipes/discount_agreement.json --markdown results/rl_recipes/discount_agreement.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def table(ledgers: dict[str, list[dict]], discounts: list[float]) -> list[dict]:
    """One row per (ledger, discount): iterations, the mean steps of its rollouts, the self agreement and the
    agreement judged by success."""
    from worldenv_core.rl.es import half_agreement

    rows = []
    for name, entries in ledgers.items():
        steps = [s for e in entries for row in e["steps"] for s in row]
        for d in discounts:
            rows.append({"ledger": name, "iterations": len(entries), "mean_steps": sum(steps) / len(steps),
                         "discount": d, "agreement": half_agreement(entries, d)["pooled"],
                         "judged_by_success": half_agreement(entries, d, judged_by=1.0)["pooled"]})
    return rows


def markdown(rows: list[dict]) -> str:
    out = ["| ledger | iterations | discount | even/odd agreement | judged by success |", "| --- | --- | --- | --- | --- |"]
    out += [f"| {r['ledger']} | {r['iterations']} | {r['discount']:g} | {r['agreement']:.2f} | {r['judged_by_success']:.2f} |"
            for r in rows]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ledgers", nargs="+", type=Path, help="ES ledger folders (iter_NNNN.json)")
    ap.add_argument("--discounts", nargs="+", type=float, default=[1.0, 0.995, 0.99, 0.98, 0.97, 0.95])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--markdown", type=Path, help="write the table here")
    args = ap.parse_args(argv)
    with user_errors():
        from worldenv_core.rl.es import read_ledger

        bad = [d for d in args.discounts if not 0 < d <= 1]
        if bad:
            raise ConfigError(f"--discounts must lie in (0, 1], got {bad}")
        ledgers = {}
        for folder in args.ledgers:
            entries = read_ledger(folder)
            if not entries:
                raise ConfigError(f"{folder}: no iter_NNNN.json (not an ES ledger)")
            ledgers[folder.name.removesuffix("_ledger")] = entries
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
