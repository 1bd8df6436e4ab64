"""Pictures people would rather look at than read: episode montages as GIF/MP4, training curves,
and `save_figure`, the one way every plot of the project is written (atomically, headless)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v2 as imageio
import numpy as np


def tile(frames: list[np.ndarray], cols: int | None = None) -> np.ndarray:
    """Tile equally sized HxWx3 images into one grid image (black where the grid is short)."""
    n = len(frames)
    cols = cols or math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    h, w, c = frames[0].shape
    grid = np.zeros((rows * h, cols * w, c), dtype=np.uint8)
    for i, f in enumerate(frames):
        r, q = divmod(i, cols)
        grid[r * h:(r + 1) * h, q * w:(q + 1) * w] = f
    return grid


MONTAGE_FRAMES = 60  # a montage's frames at most: 6 s at 10 fps, whatever the episodes' lengths


def video_picks(length: int, frames: int | None = None) -> np.ndarray:
    """Which of a video's `length` frames a montage of `frames` (default: as many as it shows of
    this video alone) plays: evenly spaced, first and last included. A caller that renders frames
    only to show them renders these (a 280-step episode: 60 renders, not 280)."""
    n = min(MONTAGE_FRAMES, length) if frames is None else frames
    return np.linspace(0, length - 1, n).round().astype(int)


def montage_video(videos: list[np.ndarray], path: str | Path, max_frames: int = MONTAGE_FRAMES, fps: int = 10) -> Path:
    """Play several episodes side by side: each video (T, H, W, 3) is resampled to the same
    number of frames, so short and long episodes start and end together."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = min(max_frames, max(len(v) for v in videos))
    picks = [video_picks(len(v), n) for v in videos]
    frames = [tile([v[idx[t]] for v, idx in zip(videos, picks)]) for t in range(n)]
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    imageio.mimsave(tmp, frames, duration=1000 / fps, loop=0) if path.suffix == ".gif" else imageio.mimsave(tmp, frames, fps=fps)
    tmp.replace(path)
    return path


def figure(*args, **kwargs):
    """`plt.subplots(...)` on the headless backend (stages run without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(*args, **kwargs)


def save_figure(fig, path: str | Path) -> Path:
    """Write `fig` as `path` (a temporary name first, renamed when complete) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)
    return path


def plot_history(history: list[dict], path: str | Path, title: str = "") -> Path:
    """One panel per logged loss/metric against the step; the history itself beside it as JSON."""
    keys = [k for k in dict.fromkeys(k for h in history for k in h) if k != "step"]  # entries may differ
    cols = min(4, max(1, len(keys)))  # a grid, not one long strip: readable at page width
    rows = -(-max(1, len(keys)) // cols)
    fig, axes = figure(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False)
    for ax in axes.flat[len(keys):]:
        ax.axis("off")
    for ax, k in zip(axes.flat, keys):
        pts = [(h["step"], h[k]) for h in history if k in h]
        ax.plot(*zip(*pts), marker="o" if len(pts) < 20 else None)
        if "success" in k and pts and pts[0][0] == 0:  # step 0 is the starting (SFT) policy: keep it in view
            ax.axhline(pts[0][1], color="grey", linestyle="--", linewidth=1, label="start (SFT)")
            ax.legend(fontsize=7)
        ax.set_title(k)
        ax.set_xlabel("step")
    fig.suptitle(title)
    fig.tight_layout()
    path = save_figure(fig, path)
    path.with_suffix(".json").write_text(json.dumps(history))
    return path
