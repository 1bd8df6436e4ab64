"""The verdict by how far into its task a context starts: paired-replay runs' pairs grouped by the
context's depth (0: an episode start, a benchmark init state or a demo's first frame; k/(n+1): the k-th
of a demo's n mid-episode frames, `mid_episode_frames`' fractions of its way to first success), each
group judged as one set. The curve says where the imagined verdict holds: a world model that drifts
over the horizon is faithful only once enough of the task is done. Depths are read per run (off the
frames each demo has in it), so runs of different context layouts pool.

    python -m analysis.verdict_depth results/libero_goal/evaluate_imagination-<starts> \\
        results/libero_goal/evaluate_imagination-<mid-episode> ... [--reflector R] [--plot depth.png]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from fractions import Fraction
from itertools import combinations
from pathlib import Path

import numpy as np

from stages.evaluate_imagination.evaluation import judged
from analysis.pooled_verdicts import judged_by, read_runs
from worldenv_core.cli import user_errors
from worldenv_core.files import write_text_atomic
from worldenv_core.viz import figure, save_figure

FIGURES = ("rollouts", "imagined_success", "real_success", "hack_rate", "hack_rate_ci95", "hacks", "f1", "auroc", "auroc_ci95")


def start_frame(row: dict) -> tuple[str, int]:
    """(episode, frame) a pair starts from: `start` is '<episode>@<frame>' for demo frames, 'task<t>/init<k>'
    ('init<k>' in pairs made before the task was named) for benchmark init states (frame 0 of a scene that
    has no episode)."""
    episode, _, frame = str(row.get("start") or row["context"]).rpartition("@")
    return (episode, int(frame)) if episode else (frame, 0)


def depths(rows: list[dict]) -> list[Fraction]:
    """Each row's depth. A demo's n mid-episode frames sit at round(end * k / (n + 1)), k = 1..n, `end` its
    first success; n is the most frames any demo has in these rows. A demo with fewer (a context dropped
    because its prefix did not replay) gets the k's that put its frames on one `end` most closely."""
    frames = defaultdict(set)
    for r in rows:
        episode, frame = start_frame(r)
        if frame:
            frames[episode].add(frame)
    n = max(map(len, frames.values()), default=0)
    ks = {}
    for episode, fs in frames.items():
        fs = sorted(fs)
        spread = lambda k: np.ptp([f * (n + 1) / ki for f, ki in zip(fs, k)])  # noqa: E731
        ks[episode] = dict(zip(fs, min(combinations(range(1, n + 1), len(fs)), key=spread)))
    out = []
    for r in rows:
        episode, frame = start_frame(r)
        zero = r.get("context_kind") == "init" or frame == 0
        out.append(Fraction(0) if zero else Fraction(ks[episode][frame], n + 1))
    return out


def by_depth(folders: list[str | Path], reflector: str | None = None, all_policies: bool = False) -> dict[str, dict]:
    """-> {depth ('0', '1/3', ...): verdict metrics of the pairs starting there}, judged by the runs' own
    reflector (their etas must agree) or by further reflector `reflector`, which must have judged every run."""
    runs, rows, at = [], [], []
    for f in folders:  # depths per run: each run's demos have its own frames
        run, run_rows = read_runs([f], all_policies)
        runs += run
        rows += run_rows
        at += depths(run_rows)
    rows, eta = judged_by(runs, rows, reflector)
    groups = defaultdict(list)
    for r, d in zip(rows, at):
        groups[d].append(r)
    return {str(d): judged(groups[d], eta) for d in sorted(groups)}


def plot_depth(out: dict[str, dict], path: str | Path, title: str = "") -> Path:
    """Imagined and real success of the same actions, and the hack rate, against the context's depth."""
    fig, ax = figure(figsize=(5, 3.6))
    x = [float(Fraction(d)) for d in out]
    for key, label, style in (("imagined_success", "imagined success", "o-"), ("real_success", "real success, same actions", "x-"),
                              ("hack_rate", "hack rate", "s--"), ("auroc", "AUROC", "^:")):
        ax.plot(x, [out[d].get(key, float("nan")) for d in out], style, label=label)
    band = np.array([out[d].get("hack_rate_ci95") or [np.nan, np.nan] for d in out], dtype=float)
    ax.fill_between(x, band[:, 0], band[:, 1], color="tab:green", alpha=0.15, lw=0, label="hack rate, 95 % (contexts)")
    for xi, d in zip(x, out):
        ax.annotate(f"{out[d]['rollouts']} pairs", (xi, 1.0), ha="center", fontsize=7)
    ax.set(xlabel="context depth (fraction of the demo's way to first success)", ylim=(-0.02, 1.08), xticks=x,
           xticklabels=list(out), title=title)
    ax.title.set_fontsize(8)
    ax.legend(fontsize=7, loc="center right")
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="evaluate_imagination output folders (fidelity.json, pairs.json)")
    p.add_argument("--reflector", help="judge by this further reflector (named as in fidelity.json's judges)")
    p.add_argument("--all-policies", action="store_true", help="every paired policy's pairs, not only the headline's")
    p.add_argument("--json", help="also write the figures here")
    p.add_argument("--plot", help="and the curve (png) here")
    args = p.parse_args(argv)
    out = by_depth(args.runs, args.reflector, args.all_policies)
    for d, m in out.items():
        print(f"depth {d}: " + ", ".join(f"{k} {m[k]}" for k in FIGURES if k in m))
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(out, indent=1, default=str))
    if args.plot:
        plot_depth(out, args.plot, title=f"verdict by context depth ({args.reflector or 'the runs’ reflector'})")
    return out


if __name__ == "__main__":
    with user_errors():
        main()
