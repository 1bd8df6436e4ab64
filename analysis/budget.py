"""Benchmark success against the real-simulator episodes each policy cost: the question the method
exists to answer ("is the world-model route worth its real episodes?").

Each policy is named with its route (a label: "LOOP, real simulator", "LOOP, imagined", "random
move") and the real episodes it consumed (collection and labelling for the imagined route, the
rollouts themselves for the real one, none for a random move). Every policy is scored on the
episodes all of them and the start ran; its gain over the start is given with a 95 % interval for a
paired difference of proportions and the exact McNemar p. The plot puts the gains against the real
episodes: a route's policies at several budgets joined in order, several at one budget (seeds) side
by side, filled where McNemar p < 0.05.

    python -m analysis.budget - --start results/s/evaluate-{A,B} \\
        --policy "LOOP, real simulator" 320 results/s/evaluate-C --policy "LOOP, real simulator" 1280 results/s/evaluate-D \\
        --policy "LOOP, imagined" 250 results/s/evaluate-E [--json F] [--plot F.png] [--tasks-plot F.png]

`--tasks-plot` draws each policy's success per task beside the start's (a grid, tasks across): a route whose
steps lift some tasks and drop others shows there, where the pooled gain hides it.
"""

from __future__ import annotations

import argparse

import numpy as np

from worldenv_core.evaluations import emit, paired_gain, pooled_policies
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.report import markdown_table


def gains_by_budget(start: dict, policies: list[tuple[str, int, dict]]) -> dict:
    """`start`: {(task, init state): success}; `policies`: (route, real episodes, outcomes) each."""
    if not policies:
        raise ConfigError("give at least one --policy")
    if any(cost < 0 for _, cost, _ in policies):
        raise ConfigError("a policy's real-episode cost cannot be negative")
    keys = sorted(set(start).intersection(*(set(p[2]) for p in policies)))
    if not keys:
        raise ConfigError("the policies and the start share no episode (task, init state)")
    base = {k: start[k] for k in keys}
    tasks = sorted({k[0] for k in keys})

    def per_task(outcomes: dict) -> dict[int, float]:
        return {t: float(np.mean([outcomes[k] for k in keys if k[0] == t])) for t in tasks}
    rows = []
    for route, cost, episodes in policies:
        g = paired_gain(base, episodes, keys)
        rows.append({"route": route, "real_episodes": int(cost), "success": float(np.mean([episodes[k] for k in keys])),
                     "gain": g["gain"], "gain_ci": g["ci"], "only_start": g["only_first"], "only_it": g["only_second"],
                     "p_value": g["p_value"], "per_task": per_task(episodes)})
    return {"episodes": len(keys), "start": float(np.mean(list(base.values()))), "start_per_task": per_task(base),
            "policies": rows}


def markdown(result: dict) -> str:
    rows = [[r["route"], r["real_episodes"], f"{100 * r['success']:.1f} %",
             f"{100 * r['gain']:+.1f} [{100 * r['gain_ci'][0]:+.1f}, {100 * r['gain_ci'][1]:+.1f}]",
             f"{r['only_start']} / {r['only_it']}", f"{r['p_value']:.3g}"] for r in result["policies"]]
    return "\n".join([*markdown_table(["route", "real episodes", "success", "gain over the start (points, 95 %)",
                                       "only the start / only it", "McNemar p"], rows), "",
                      f"over {result['episodes']} episodes every policy ran; the start solves "
                      f"{100 * result['start']:.1f} %"]) + "\n"


def plot(result: dict, path: str) -> None:
    from worldenv_core.viz import figure, save_figure

    fig, ax = figure(figsize=(6.2, 3.6))
    span = max([r["real_episodes"] for r in result["policies"]] + [1])
    routes = list(dict.fromkeys(r["route"] for r in result["policies"]))
    for c, route in enumerate(routes):
        mine = [r for r in result["policies"] if r["route"] == route]
        costs = sorted({r["real_episodes"] for r in mine})
        for cost in costs:
            here = [r for r in mine if r["real_episodes"] == cost]
            offsets = np.linspace(-0.012, 0.012, len(here)) * span if len(here) > 1 else [0.0]
            for dx, r in zip(offsets, here):
                y, (lo, hi) = 100 * r["gain"], (100 * r["gain_ci"][0], 100 * r["gain_ci"][1])
                ax.errorbar(cost + dx, y, yerr=[[y - lo], [hi - y]], fmt="o", color=f"C{c}", ms=6, capsize=2, lw=0.8,
                            mfc=f"C{c}" if r["p_value"] < 0.05 else "white", label=route if r is mine[0] else None)
        if len(costs) > 1:  # a route at several budgets: its mean gain per budget, in order
            ax.plot(costs, [100 * np.mean([r["gain"] for r in mine if r["real_episodes"] == k]) for k in costs],
                    "-", color=f"C{c}", lw=1)
    ax.axhline(0, color="grey", lw=0.8, ls="--")
    ax.set(xlabel="real-simulator episodes consumed", ylabel="real success - start (points)")
    ax.set_title(f"{result['episodes']} benchmark episodes; the start solves {100 * result['start']:.1f} %\n"
                 "(95 % paired intervals; filled: McNemar p < 0.05 against the start)", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    save_figure(fig, path)


def tasks_plot(result: dict, path: str) -> None:
    """Success per task: the start's row on top, then each policy's (labelled route, real episodes), with the
    change against the start printed in each cell."""
    from worldenv_core.viz import figure, save_figure

    tasks = sorted(result["start_per_task"], key=int)
    rows = [("start", result["start_per_task"])] + [(f"{r['route']}, {r['real_episodes']}", r["per_task"])
                                                     for r in result["policies"]]
    grid = np.array([[100 * row[t] for t in tasks] for _, row in rows])
    fig, ax = figure(figsize=(1.0 + 0.55 * len(tasks), 0.8 + 0.32 * len(rows)))
    ax.imshow(grid, cmap="viridis", vmin=0, vmax=100, aspect="auto")
    for i in range(len(rows)):
        for j in range(len(tasks)):
            delta = "" if i == 0 else f"\n{grid[i, j] - grid[0, j]:+.0f}"
            ax.text(j, i, f"{grid[i, j]:.0f}{delta}", ha="center", va="center", fontsize=6,
                    color="white" if grid[i, j] < 55 else "black")
    ax.set_xticks(range(len(tasks)), [f"task {t}" for t in tasks], fontsize=7)
    ax.set_yticks(range(len(rows)), [name for name, _ in rows], fontsize=7)
    ax.set_title("success per task, % (below: points against the start)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--start", nargs="+", required=True, help="evaluations of the policy every route updates (pooled)")
    p.add_argument("--policy", nargs="+", action="append", required=True, metavar="ROUTE EPISODES EVALUATION",
                   help="a route's label, the real episodes the policy consumed, then its evaluations (pooled); "
                        "repeat per policy")
    p.add_argument("--json", help="also write the result here")
    p.add_argument("--plot", help="also draw each policy's gain against its real episodes here (.png)")
    p.add_argument("--tasks-plot", help="also draw each policy's success per task beside the start's here (.png)")
    args = p.parse_args(argv)
    for entry in args.policy:
        if len(entry) < 3 or not entry[1].isdigit():
            raise ConfigError(f"--policy {' '.join(entry)}: give a route's label, its real episodes as a whole "
                              f"number, then at least one evaluation")
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    sides = pooled_policies(manifest, [args.start] + [e[2:] for e in args.policy])
    result = gains_by_budget(sides[0][0], [(e[0], int(e[1]), s[0]) for e, s in zip(args.policy, sides[1:])])
    result.update(records={"start": args.start, "policies": args.policy},
                  termination=sides[0][1]["termination"], suite=sides[0][1]["suite"])
    if args.tasks_plot:
        tasks_plot(result, args.tasks_plot)
    return emit(result, markdown(result), args.json, plot, args.plot)


if __name__ == "__main__":
    with user_errors():
        main()
