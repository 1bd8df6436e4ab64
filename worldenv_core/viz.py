"""Pictures people would rather look at than read: episode montages as GIF/MP4."""

from __future__ import annotations

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


def montage_video(videos: list[np.ndarray], path: str | Path, max_frames: int = 60, fps: int = 10) -> Path:
    """Play several episodes side by side: each video (T, H, W, 3) is resampled to the same
    number of frames, so short and long episodes start and end together."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = min(max_frames, max(len(v) for v in videos))
    picks = [np.linspace(0, len(v) - 1, n).round().astype(int) for v in videos]
    frames = [tile([v[idx[t]] for v, idx in zip(videos, picks)]) for t in range(n)]
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    imageio.mimsave(tmp, frames, duration=1000 / fps, loop=0) if path.suffix == ".gif" else imageio.mimsave(tmp, frames, fps=fps)
    tmp.replace(path)
    return path
