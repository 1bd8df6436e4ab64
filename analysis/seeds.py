"""Does one way of updating a policy beat another, when each seed is one draw of it?

`paired` asks whether two *policies* differ on the same episodes. A training seed is a draw of the
procedure, though: two seeds of the same update (or two random moves of the weights) can differ by
several points, significantly, on 500 episodes. So the question "does LOOP lift this policy more
than a random move of the same size" has the policies, not the episodes, as its units. This takes
several policies per procedure (each pooled over its evaluations, as `paired` pools them), scores
every policy on the episodes all of them ran, and tests the procedures' mean success exactly by
permutation over the policies' labels (every split of the policies into groups of those sizes; with
a handful of seeds no distributional assumption is worth making). With the start given, each policy's gain over it and its own paired
McNemar p are listed too: what one seed alone would have claimed.

    python -m analysis.seeds - --start results/s/evaluate-{A,B} \\
        --policy method results/s/evaluate-C --policy method results/s/evaluate-D \\
        --policy random results/s/evaluate-E --policy random results/s/evaluate-F [--json F] [--plot F.png]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from worldenv_core.evaluations import emit, pooled_policies
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.stats import paired_success_test, permutation_p
from worldenv_core.report import markdown_table


def compare_procedures(policies: dict[str, list[dict]], start: dict | None = None) -> dict:
    """`policies`: {procedure: [{(task, init state): success} per seed]}, two procedures."""
    if len(policies) != 2:
        raise ConfigError(f"give policies of exactly two procedures, not {sorted(policies)}")
    if any(len(seeds) < 1 for seeds in policies.values()):
        raise ConfigError("each procedure needs at least one policy")
    every = [s for seeds in policies.values() for s in seeds] + ([start] if start is not None else [])
    keys = sorted(set(every[0]).intersection(*every[1:]))
    if not keys:
        raise ConfigError("the policies share no episode (task, init state)")
    base = float(np.mean([start[k] for k in keys])) if start is not None else None
    groups, rates = {}, {}
    for name, seeds in policies.items():
        rows = []
        for episodes in seeds:
            row = {"success": float(np.mean([episodes[k] for k in keys]))}
            if start is not None:
                test = paired_success_test({k: start[k] for k in keys}, {k: episodes[k] for k in keys})
                row.update(gain=row["success"] - base, only_start=test["only_a"], only_it=test["only_b"],
                           p_value=test["p_value"])
            rows.append(row)
        rates[name] = np.array([r["success"] for r in rows])
        groups[name] = {"policies": rows, "mean": float(rates[name].mean()),
                        "sd": float(rates[name].std(ddof=1)) if len(rows) > 1 else None}
    (first, a), (second, b) = rates.items()
    result = {"episodes": len(keys), "start": base, "procedures": groups, "difference": float(a.mean() - b.mean()),
              "permutation_p": permutation_p(a, b), "relabellings": math.comb(len(a) + len(b), len(a))}
    return result


def markdown(result: dict) -> str:
    rows = []
    for name, group in result["procedures"].items():
        for i, r in enumerate(group["policies"]):
            vs = ([f"{100 * r['gain']:+.1f}", f"{r['only_start']} / {r['only_it']}", f"{r['p_value']:.3g}"]
                  if "gain" in r else ["", "", ""])
            rows.append([name, i, f"{100 * r['success']:.1f} %", *vs])
    (first, g1), (second, g2) = result["procedures"].items()
    sd = lambda g: f", seed SD {100 * g['sd']:.1f}" if g["sd"] is not None else ""  # noqa: E731
    start = f"the start solves {100 * result['start']:.1f} %; " if result["start"] is not None else ""
    return "\n".join([*markdown_table(["procedure", "policy", "success", "gain over the start (points)",
                                       "only the start / only it", "McNemar p"], rows), "",
                      f"over {result['episodes']} episodes every policy ran: {start}{first} "
                      f"{100 * g1['mean']:.1f} % ({len(g1['policies'])} policies{sd(g1)}), {second} "
                      f"{100 * g2['mean']:.1f} % ({len(g2['policies'])}{sd(g2)}); difference "
                      f"{100 * result['difference']:+.1f} points, exact permutation p = {result['permutation_p']:.3g} "
                      f"over {result['relabellings']} relabellings of the policies"]) + "\n"


def plot(result: dict, path: str) -> None:
    from worldenv_core.viz import figure, save_figure

    fig, ax = figure(figsize=(4.5, 3.2))
    ref = result["start"] or 0.0
    for x, (name, group) in enumerate(result["procedures"].items()):
        ys = [100 * (r["success"] - ref) for r in group["policies"]]
        sig = [r.get("p_value", 1.0) < 0.05 for r in group["policies"]]
        jitter = np.linspace(-0.08, 0.08, len(ys)) if len(ys) > 1 else [0.0]
        for j, y, s in zip(jitter, ys, sig):
            ax.plot(x + j, y, "o", color="C0" if x == 0 else "C1", mfc="none" if not s else None, ms=7)
        ax.hlines(np.mean(ys), x - 0.2, x + 0.2, color="k")
    ax.axhline(0, color="grey", lw=0.8, ls="--")
    ax.set_xticks(range(len(result["procedures"])), list(result["procedures"]))
    ax.set_xlim(-0.6, len(result["procedures"]) - 0.4)
    ax.set_ylabel("real success - start (points)" if result["start"] is not None else "real success (%)")
    ax.set_title(f"{result['episodes']} episodes; permutation p = {result['permutation_p']:.2g}\n"
                 "(filled: McNemar p < 0.05 against the start)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--start", nargs="+", help="evaluations of the policy both procedures update (pooled)")
    p.add_argument("--policy", nargs="+", action="append", required=True, metavar="PROCEDURE EVALUATION",
                   help="a procedure's name, then the evaluations of one of its policies (pooled); repeat per policy")
    p.add_argument("--json", help="also write the result here")
    p.add_argument("--plot", help="also draw each policy's gain per procedure here (.png)")
    args = p.parse_args(argv)
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    if any(len(entry) < 2 for entry in args.policy):
        raise ConfigError("each --policy is a procedure's name followed by at least one evaluation")
    sides = pooled_policies(manifest, ([args.start] if args.start else []) + [e[1:] for e in args.policy])
    start = sides.pop(0)[0] if args.start else None
    policies: dict[str, list[dict]] = {}
    for entry, (episodes, _) in zip(args.policy, sides):
        policies.setdefault(entry[0], []).append(episodes)
    result = compare_procedures(policies, start)
    result.update(records={"start": args.start, "policies": args.policy},
                  termination=sides[0][1]["termination"], suite=sides[0][1]["suite"])
    return emit(result, markdown(result), args.json, plot, args.plot)


if __name__ == "__main__":
    with user_errors():
        main()
