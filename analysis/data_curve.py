"""What exploration data buys a world model, as curves: kept paired-replay checks of world models trained
on 0, 250, 500, ... policy rollouts (beside the demos), each under one or more generators (the one-step mean,
a sampled one), read into one table and figure by the number of rollouts: the imagined verdict's AUROC
against the real outcome of the same actions, its hack rate (imagined successes that fail for real), recall,
and imagined beside real success. Each point is one `evaluate_imagination` run at the same contexts, or one
`analysis.imagined_ledger --json` result: the real route's ES members replayed from their placements' starts, where
the members differ (its point also carries the step's cosine with the real one, with the verdict and with the
reflector's R as the return; AUROC is not measured there).

    python -m analysis.data_curve --point 0 mean results/libero_spatial/evaluate_imagination-<a> \\
        --point 250 mean results/libero_spatial/evaluate_imagination-<b> \\
        --point 250 sampled results/libero_spatial/evaluate_imagination-<c> \\
        --point 0 "from starts" results/rl_recipes/imagined_ledger_<d>.json [--json curve.json] [--plot curve.png]
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.files import write_text_atomic
from worldenv_core.viz import figure, save_figure

FIGURES = ("rollouts", "imagined_success", "real_success", "auroc", "recall", "precision", "hack_rate", "hacks",
           "imagined_mixed_groups", "step_cosine", "reward_step_cosine")


def read_point(folder: str | Path) -> dict:
    """The headline verdict figures of one kept paired-replay run (a folder) or ES-ledger replay (a json file),
    plus the record it came from."""
    if Path(folder).suffix == ".json":
        return read_ledger_point(folder)
    path = Path(folder) / "fidelity.json"
    if not path.is_file():
        raise FileNotFoundError(f"no fidelity.json in {folder}: give an evaluate_imagination output folder or an "
                                "imagined_ledger json")
    run = json.loads(path.read_text())
    return {**{k: run["headline"].get(k) for k in FIGURES}, "record": run.get("record", Path(folder).name)}


def read_ledger_point(path: str | Path) -> dict:
    """`analysis.imagined_ledger --json`'s pooled figures in the curve's terms: every member-placement episode is a
    pair, a context is a placement (split in imagination when its members' verdicts differ)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no imagined_ledger result at {path}")
    run = json.loads(path.read_text())
    if "pooled" not in run or "iterations" not in run:
        raise ValueError(f"{path} is not an imagined_ledger --json result (no pooled figures)")
    rows, pooled = list(run["iterations"].values()), run["pooled"]
    imagined = sum(r["imagined_successes"] for r in rows)
    hacks = imagined - sum(r["both_succeed"] for r in rows)
    contexts = [c for r in rows for c in r["imagined_by_context"]]
    return {"rollouts": pooled["episodes"], "imagined_success": pooled["imagined_success"],
            "real_success": pooled["real_success"], "auroc": None, "recall": pooled["recall"],
            "precision": 1 - pooled["hack_rate"], "hack_rate": pooled["hack_rate"], "hacks": hacks,
            "imagined_mixed_groups": sum(0 < c < 1 for c in contexts) / len(contexts) if contexts else None,
            "step_cosine": pooled["step_cosine"], "reward_step_cosine": pooled.get("reward_step_cosine"),
            "record": path.stem}


def data_curve(points: list[tuple[int, str, str | Path]]) -> dict[str, list[dict]]:
    """-> {generator: [{"exploration_rollouts": n, figures...}, ...] in order of n}."""
    curves = defaultdict(list)
    for n, generator, folder in points:
        if int(n) < 0:
            raise ValueError(f"a point's number of exploration rollouts must be >= 0, got {n}")
        curves[generator].append({"exploration_rollouts": int(n), **read_point(folder)})
    return {g: sorted(rows, key=lambda r: r["exploration_rollouts"]) for g, rows in curves.items()}


def table(curves: dict[str, list[dict]]) -> str:
    """A markdown table, one row per point."""
    def fmt(v):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}" if isinstance(v, float) else str(v)
    head = ["generator", "exploration rollouts", "pairs", "imagined", "real", "AUROC", "recall", "precision", "hack rate",
            "step cosine (verdict / R)", "run"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g, rows in curves.items():
        for r in rows:
            cells = [g, r["exploration_rollouts"], r["rollouts"], r["imagined_success"], r["real_success"], r["auroc"],
                     r["recall"], r["precision"], r["hack_rate"]]
            cosines = "-" if r.get("step_cosine") is None and r.get("reward_step_cosine") is None else \
                f"{fmt(r.get('step_cosine'))} / {fmt(r.get('reward_step_cosine'))}"
            lines.append("| " + " | ".join([*(fmt(c) for c in cells), cosines, r["record"]]) + " |")
    return "\n".join(lines)


def plot_curve(curves: dict[str, list[dict]], path: str | Path, title: str = "") -> Path:
    """Left: AUROC and hack rate by rollouts; right: imagined and real success of the same actions."""
    fig, (left, right) = figure(1, 2, figsize=(10, 5.2))

    def values(rows, key):  # a figure a point did not measure (AUROC from starts) is left out of its line
        return [math.nan if r.get(key) is None else r[key] for r in rows]

    for i, (g, rows) in enumerate(curves.items()):
        x = [r["exploration_rollouts"] for r in rows]
        color = f"C{i}"
        if any(r.get("auroc") is not None for r in rows):
            left.plot(x, values(rows, "auroc"), "o-", color=color, label=f"AUROC ({g})")
        left.plot(x, values(rows, "hack_rate"), "s--", color=color, label=f"hack rate ({g})")
        right.plot(x, values(rows, "imagined_success"), "o-", color=color, label=f"imagined ({g})")
        right.plot(x, values(rows, "real_success"), "x:", color=color, label=f"real, same actions ({g})")
    for ax, name in ((left, "the verdict"), (right, "success")):
        ax.set(xlabel="exploration rollouts in the world model's data", ylim=(-0.02, 1.02), title=name)
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)  # below: the lines stay visible
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--point", nargs=3, action="append", required=True, metavar=("ROLLOUTS", "GENERATOR", "RUN"),
                   help="exploration rollouts in the world model's data, the generator's (or the contexts') name, the kept "
                        "run's folder or an imagined_ledger json")
    p.add_argument("--json", help="also write the curves here")
    p.add_argument("--plot", help="and the figure (png) here")
    p.add_argument("--title", default="")
    args = p.parse_args(argv)
    curves = data_curve([(int(n), g, f) for n, g, f in args.point])
    print(table(curves))
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(curves, indent=1, default=str))
    if args.plot:
        plot_curve(curves, args.plot, args.title)
    return curves


if __name__ == "__main__":
    with user_errors():
        main()
