"""A Hydra sweep over eta and N (`python -m stages.post_train_loop -m eta=0.3,0.5,0.7
rl.n_rollouts=4,8`), summarised: each run of a sweep is tagged with its multirun folder, and the
summary (a table, and real success, imagined reward and hack rate against eta, one line per N)
is written into that folder after every run and drawn again in the experiment report.

The same summary for a sweep run from a context pack on a GPU host: `analysis.sweep_packs`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import StageRecord
from worldenv_core.report import markdown_table
from worldenv_core.viz import figure, save_figure

# what a sweep compares: the record's metric (an {iteration: value} curve) and how it is named
MEASURES = (("real_success", "real success"), ("imagined_reward", "imagined reward"),
            ("paired_hack_rate", "paired hack rate"))


def sweep_dir() -> Path | None:
    """The multirun folder of this job when it runs in a Hydra sweep (`-m`), else None."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    return Path(HydraConfig.get().sweep.dir)


def _ends(curve: dict | None) -> tuple[float | None, float | None]:
    """(first, last) value of an {iteration: value} curve."""
    if not curve:
        return None, None
    steps = sorted(curve, key=int)
    return curve[steps[0]], curve[steps[-1]]


def summary_rows(runs: list[StageRecord]) -> list[dict]:
    """One row per point of the sweep, ordered by N then eta: each measure at the start (the SFT
    policy, iteration 0) and at the end."""
    newest = {(r.tags.get("eta"), r.tags.get("n_rollouts")): r for r in runs}  # a point re-run: its newest record
    rows = []
    for r in newest.values():
        row = {"eta": r.tags.get("eta"), "n_rollouts": r.tags.get("n_rollouts"), "run": r.id,
               "iterations": r.metrics.get("iterations"), "kept_groups": r.metrics.get("kept_groups")}
        for key, _ in MEASURES:
            row[f"{key}_first"], row[f"{key}_last"] = _ends(r.metrics.get(key))
        rows.append(row)
    return sorted(rows, key=lambda x: (x["n_rollouts"] or 0, x["eta"] if x["eta"] is not None else -1))


def _fmt(x, pct: bool = True) -> str:
    if x is None or (isinstance(x, float) and np.isnan(x)):
        return ""
    return f"{100 * x:.1f} %" if pct else f"{x:.3f}"


def summary_table(rows: list[dict]) -> list[str]:
    return markdown_table(
        ["eta", "N", "iterations", "real success (SFT -> last)", "imagined reward (SFT -> last)",
         "paired hack rate (SFT -> last)", "groups kept", "run"],
        [[r["eta"], r["n_rollouts"], r["iterations"],
          f"{_fmt(r['real_success_first'])} -> {_fmt(r['real_success_last'])}" + _paired(r),
          f"{_fmt(r['imagined_reward_first'], False)} -> {_fmt(r['imagined_reward_last'], False)}",
          f"{_fmt(r['paired_hack_rate_first'])} -> {_fmt(r['paired_hack_rate_last'])}",
          _fmt(r["kept_groups"]), f"`{r['run']}`"] for r in rows])


def _paired(row: dict) -> str:
    """A pack point's real comparison: the episodes only one side solved, and McNemar's p."""
    if row.get("real_p") is None:
        return ""
    return f" ({row['real_only_first']} / {row['real_only_last']}, p {row['real_p']:.2f}, {row['real_episodes']} eps)"


def plot_summary(rows: list[dict], path: Path) -> Path:
    """Each measure at the end of training against eta, one line per N (the SFT level dotted)."""
    fig, axes = figure(ncols=len(MEASURES), figsize=(4 * len(MEASURES), 3.3))
    for ax, (key, label) in zip(axes, MEASURES):
        for n in sorted({r["n_rollouts"] for r in rows}, key=lambda v: v or 0):
            got = [(r["eta"], r[f"{key}_last"]) for r in rows if r["n_rollouts"] == n and r[f"{key}_last"] is not None
                   and r["eta"] is not None]
            if got:
                ax.plot([e for e, _ in got], [v for _, v in got], "-o", ms=4, label=f"N={n}")
        base = [r[f"{key}_first"] for r in rows if r[f"{key}_first"] is not None]
        if base:
            ax.axhline(float(np.mean(base)), color="k", ls=":", lw=0.8, label="SFT")
        ax.set(xlabel="eta", title=label)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def write_summary(folder: Path, runs: list[StageRecord] | None = None, rows: list[dict] | None = None) -> Path:
    """sweep_summary.{json,md,png} in the multirun folder (rewritten as each run finishes), from the
    sweep's records or from rows made otherwise (`pack_rows`)."""
    rows = summary_rows(runs) if rows is None else rows
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in (("sweep_summary.json", json.dumps(rows, indent=1)),
                       ("sweep_summary.md", "\n".join(summary_table(rows)) + "\n")):
        write_text_atomic(folder / name, text)
    return plot_summary(rows, folder / "sweep_summary.png")
