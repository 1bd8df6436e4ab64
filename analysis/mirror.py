"""Does an update gain by its direction or by its size? A move and its mirror against their start.

A policy moved off its start by an update d, and the start moved by -d (`python -m
analysis.random_update --mirror`), evaluated on the same episodes as the start. Near
the start the success of a move is f(d) ~ f(0) + g.d + d'Hd/2: the first-order part flips sign with
the move, the second-order part does not. So half the difference of the two gains estimates what the
update's direction adds (the part a reward can point; a random direction's is zero on average), and
half their sum what a move of that size does wherever it points (a start that sits low in its
neighbourhood gains both ways). Per move: each side's paired gain over the start (95 % interval,
McNemar p), the direction part (exact McNemar of the move against its mirror) and the size part
(exact test that the start is the odd one out among the three, `odd_one_out`).

Does a reward point its updates up more often, or more steeply, than chance points a random direction?
`--procedure NAME K...` groups moves (numbered 1, 2, ... in the order of `--move`) as draws of one
procedure: per procedure how many direction parts are positive (one-sided sign test: a random direction
points up half the time) and, for two procedures, the exact permutation p that the first one's parts
are larger (one-sided, over every split of the moves into groups of those sizes).

    python -m analysis.mirror - --start results/s/evaluate-{A,B} \\
        --move "LOOP, real simulator" results/s/evaluate-C --mirror results/s/evaluate-D \\
        --move "random move" results/s/evaluate-E --mirror results/s/evaluate-F \\
        [--procedure RL 1 --procedure random 2] [--json F] [--plot F.png]
"""

from __future__ import annotations

import argparse
import math
import textwrap

import numpy as np

from analysis.odd_one_out import odd_one_out
from worldenv_core.evaluations import emit, paired_gain, pooled_policies
from worldenv_core.stats import fair_coin_tail, permutation_p
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.report import markdown_table


def direction_and_size(start: dict, moves: list[tuple[str, dict, dict]]) -> dict:
    """`start`: {(task, init state): success}; `moves`: (label, the moved policy's, its mirror's) each."""
    if not moves:
        raise ConfigError("give at least one --move with its --mirror")
    keys = sorted(set(start).intersection(*(set(m[1]) & set(m[2]) for m in moves)))
    if not keys:
        raise ConfigError("the moves, their mirrors and the start share no episode (task, init state)")
    rows = []
    for label, plus, minus in moves:
        between = paired_gain(minus, plus, keys)  # the move against its mirror: 2 x the direction part
        x0, xp, xm = (np.array([side[k] for k in keys], dtype=float) for side in (start, plus, minus))
        even = (xp + xm) / 2 - x0  # per episode: the size part's estimate
        half = 1.96 * float(even.std(ddof=1)) / math.sqrt(len(keys)) if len(keys) > 1 else float("nan")
        rows.append({"label": label, "move": paired_gain(start, plus, keys), "mirror": paired_gain(start, minus, keys),
                     "direction": between["gain"] / 2, "direction_ci": [v / 2 for v in between["ci"]],
                     "only_mirror": between["only_first"], "only_move": between["only_second"],
                     "direction_p": between["p_value"], "size": float(even.mean()),
                     "size_ci": [float(even.mean()) - half, float(even.mean()) + half],
                     "size_p": odd_one_out({k: start[k] for k in keys}, [plus, minus])["p_value"]})
    return {"episodes": len(keys), "start": float(np.mean([start[k] for k in keys])), "moves": rows}


def compare_directions(result: dict, procedures: dict[str, list[int]]) -> dict:
    """`procedures`: {name: 1-based numbers of `result`'s moves}. -> each one's direction parts, how many point
    up and the one-sided sign test; for two, the one-sided exact permutation p that the first's are larger."""
    moves, seen = result["moves"], set()
    for name, numbers in procedures.items():
        if not numbers:
            raise ConfigError(f"procedure {name!r} names no move")
        for k in numbers:
            if not 1 <= k <= len(moves):
                raise ConfigError(f"procedure {name!r}: move {k} does not exist (moves are numbered 1 to {len(moves)})")
            if k in seen:
                raise ConfigError(f"move {k} ({moves[k - 1]['label']!r}) is in two procedures")
            seen.add(k)
    out: dict = {"procedures": {}}
    for name, numbers in procedures.items():
        parts = [moves[k - 1]["direction"] for k in numbers]
        up = sum(part > 0 for part in parts)
        sign_p = fair_coin_tail(len(parts), len(parts) - up)  # P(at least `up` of them up by chance)
        out["procedures"][name] = {"moves": numbers, "directions": parts, "mean": float(np.mean(parts)),
                                   "up": up, "sign_p": sign_p}
    if len(procedures) == 2:
        (first, a), (second, b) = ((n, np.array(g["directions"])) for n, g in out["procedures"].items())
        out.update(difference=float(a.mean() - b.mean()), permutation_p=permutation_p(a, b, greater=True),
                   relabellings=math.comb(len(a) + len(b), len(a)), first=first, second=second)
    return out


def _points(value: float, ci: list[float]) -> str:
    return f"{100 * value:+.1f} [{100 * ci[0]:+.1f}, {100 * ci[1]:+.1f}]"


def markdown(result: dict) -> str:
    rows = [[r["label"], f"{_points(r['move']['gain'], r['move']['ci'])}, p {r['move']['p_value']:.3g}",
             f"{_points(r['mirror']['gain'], r['mirror']['ci'])}, p {r['mirror']['p_value']:.3g}",
             f"{_points(r['direction'], r['direction_ci'])}", f"{r['only_mirror']} / {r['only_move']}, p {r['direction_p']:.3g}",
             f"{_points(r['size'], r['size_ci'])}, p {r['size_p']:.3g}"] for r in result["moves"]]
    head = ["move", "its gain over the start (points, 95 %)", "its mirror's gain", "direction part (gain - mirror's) / 2",
            "only the mirror / only the move", "size part (gain + mirror's) / 2"]
    return "\n".join([*markdown_table(head, rows), "",
                      f"over {result['episodes']} episodes every policy ran; the start solves {100 * result['start']:.1f} %; "
                      "p: exact McNemar (gains, direction), exact odd-one-out test of the start among the three (size)",
                      *_procedures_markdown(result.get("by_procedure"))]) + "\n"


def _procedures_markdown(by: dict | None) -> list[str]:
    if not by:
        return []
    parts = [f"{name} {100 * g['mean']:+.1f} on average, {g['up']} of {len(g['directions'])} up (sign test p {g['sign_p']:.3g})"
             for name, g in by["procedures"].items()]
    lines = ["", "direction parts by procedure (one-sided tests): " + "; ".join(parts)]
    if "permutation_p" in by:
        lines[-1] += (f"; {by['first']} - {by['second']} {100 * by['difference']:+.1f} points, exact permutation "
                      f"p = {by['permutation_p']:.3g} over {by['relabellings']} splits of the moves")
    return lines


def plot(result: dict, path: str) -> None:
    from worldenv_core.viz import figure, save_figure

    rows = result["moves"]
    fig, ax = figure(figsize=(max(4.8, 1.6 + 1.6 * len(rows)), 3.8))
    for i, r in enumerate(rows):
        for dx, side, marker, name in ((-0.15, r["move"], "o", "the move"), (0.15, r["mirror"], "v", "its mirror")):
            y, (lo, hi) = 100 * side["gain"], (100 * side["ci"][0], 100 * side["ci"][1])
            ax.errorbar(i + dx, y, yerr=[[y - lo], [hi - y]], fmt=marker, color="C0" if dx < 0 else "C1", ms=6,
                        capsize=2, lw=0.8, mfc=("C0" if dx < 0 else "C1") if side["p_value"] < 0.05 else "white",
                        label=name if i == 0 else None)
        ax.plot([i - 0.15, i + 0.15], [100 * r["move"]["gain"], 100 * r["mirror"]["gain"]], "-", color="grey", lw=0.8)
        ax.plot([i], [100 * r["size"]], "_", color="k", ms=14, mew=1.5, label="size part (mean of the two)" if i == 0 else None)
    ax.axhline(0, color="grey", lw=0.8, ls="--")
    # Wrapped: seven or more moves' labels would run into each other on one line.
    ax.set_xticks(range(len(rows)), [textwrap.fill(r["label"], 22) for r in rows], fontsize=7)
    ax.set(ylabel="real success - start (points)", xlim=(-0.6, len(rows) - 0.4))
    ax.set_title(f"the start solves {100 * result['start']:.1f} % of {result['episodes']} episodes\n"
                 "95 % paired intervals; filled: McNemar p < 0.05 against it", fontsize=8)
    fig.legend(fontsize=7, loc="lower center", ncol=3, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    save_figure(fig, path)


def _procedure_numbers(entries: list[list[str]]) -> dict[str, list[int]]:
    procedures: dict[str, list[int]] = {}
    for name, *numbers in entries:
        if not numbers or not all(k.isdigit() for k in numbers):
            raise ConfigError(f"--procedure {name} {' '.join(numbers)}: give a name, then move numbers (1, 2, ...)")
        if name in procedures:
            raise ConfigError(f"--procedure {name} is given twice: list all its moves once")
        procedures[name] = [int(k) for k in numbers]
    return procedures


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--start", nargs="+", required=True, help="evaluations of the policy both sides moved from (pooled)")
    p.add_argument("--move", nargs="+", action="append", required=True, metavar="LABEL EVALUATION",
                   help="a label, then the moved policy's evaluations (pooled); repeat per move")
    p.add_argument("--mirror", nargs="+", action="append", required=True, metavar="EVALUATION",
                   help="the mirrored policy's evaluations (pooled), one --mirror per --move, in order")
    p.add_argument("--procedure", nargs="+", action="append", default=[], metavar="NAME K",
                   help="a procedure's name, then the numbers (1, 2, ... in --move order) of its moves; "
                        "repeat per procedure")
    p.add_argument("--json", help="also write the result here")
    p.add_argument("--plot", help="also draw each move's and its mirror's gain here (.png)")
    args = p.parse_args(argv)
    procedures = _procedure_numbers(args.procedure)
    if len(args.move) != len(args.mirror):
        raise ConfigError(f"{len(args.move)} --move but {len(args.mirror)} --mirror: give one mirror per move")
    for entry in args.move:
        if len(entry) < 2:
            raise ConfigError(f"--move {' '.join(entry)}: give a label, then at least one evaluation")
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    sides = pooled_policies(manifest, [args.start] + [e[1:] for e in args.move] + args.mirror)
    n = len(args.move)
    result = direction_and_size(sides[0][0], [(e[0], sides[1 + i][0], sides[1 + n + i][0])
                                              for i, e in enumerate(args.move)])
    if procedures:
        result["by_procedure"] = compare_directions(result, procedures)
    result.update(records={"start": args.start, "moves": args.move, "mirrors": args.mirror},
                  termination=sides[0][1]["termination"], suite=sides[0][1]["suite"])
    return emit(result, markdown(result), args.json, plot, args.plot)


if __name__ == "__main__":
    with user_errors():
        main()
