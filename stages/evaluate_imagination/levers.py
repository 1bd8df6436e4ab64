"""The levers of verdict fidelity side by side: every (world model, reflector) the held-out pairs were
judged with, its AUROC, F1 and precision (1 - hack rate) against the targets, in one plot the
report shows under the fidelity table. A run's terminating reflector and each further reflector
judging its pairs (`more_reflectors`) are one bar group each; the newest judgement of a pairing wins."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worldenv_core.viz import figure, save_figure

FIGURES = (("auroc", "AUROC", 0.90), ("f1", "F1", 0.80), ("precision", "1 - hack rate", 0.90))


def lever_rows(judgements: list[tuple[str, str, dict]]) -> dict[str, dict]:
    """(world model, reflector, verdict metrics) oldest first -> label -> figures, newest kept."""
    out = {}
    for worldsim, reflector, m in judgements:
        label = f"{worldsim} + {reflector}"
        out.pop(label, None)  # re-inserted: the newest judgement of a pairing sorts last
        hack = m.get("hack_rate")
        out[label] = {"auroc": m.get("auroc"), "f1": m.get("f1"),
                      "precision": None if hack is None or np.isnan(hack) else 1.0 - hack, "rollouts": m.get("rollouts")}
    return out


def plot_levers(rows: dict[str, dict], path: Path) -> Path:
    """Grouped horizontal bars per pairing, the targets as dashed lines; a missing figure (no
    imagined success: no precision) is left empty."""
    labels = list(rows)
    fig, ax = figure(figsize=(7, 0.9 + 0.75 * len(labels)))
    y = np.arange(len(labels))
    height = 0.8 / len(FIGURES)
    for i, (key, name, target) in enumerate(FIGURES):
        values = [np.nan if rows[lab][key] is None else rows[lab][key] for lab in labels]
        bars = ax.barh(y + (i - 1) * height, np.nan_to_num(values), height, label=f"{name} (target {target:g})")
        ax.vlines(target, y[0] - 0.5, y[-1] + 0.5, colors=bars.patches[0].get_facecolor(), linestyles="--", lw=1)
    for yi, lab in zip(y, labels):
        if all(rows[lab][key] is None or np.isnan(rows[lab][key]) for key, _, _ in FIGURES):
            ax.text(0.01, yi, "undefined: no real or no imagined success", va="center", fontsize=7)
    ax.set_yticks(y, [f"{lab} ({rows[lab]['rollouts']} pairs)" for lab in labels], fontsize=7)
    ax.invert_yaxis()  # oldest on top, the newest lever at the bottom
    ax.set(xlim=(0, 1), xlabel="imagined verdict vs real outcome, same actions",
           title="verdict fidelity by lever (held-out pairs)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return save_figure(fig, path)
