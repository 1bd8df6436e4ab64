"""Data for training steps: the device, endless seeded batches that resume exactly, and the
per-step seeds and augmentation every training stage uses the same way."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from itertools import count
from typing import TypeVar

import torch
from torch.utils.data import DataLoader, Dataset, Subset

T = TypeVar("T")


def pick_device(name: str = "auto") -> torch.device:
    """`auto`: CUDA when there is one. A rank of a torchrun launch gets its own GPU (LOCAL_RANK)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and device.index is None and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def batches(dataset: Dataset, batch_size: int, seed: int, start_step: int = 0, num_workers: int = 0,
            weights: torch.Tensor | None = None) -> Iterator[dict]:
    """Endless shuffled batches. Epoch e is a permutation drawn with seed + e, and a run resumed at
    step s starts at batch s of that order, so it sees exactly the batches an uninterrupted run
    would (resume is bit-identical). The loader gets its own generator: creating one draws a seed,
    which must not come from the global RNG that augmentation and dropout use.

    `weights` (one per item, not all zero): an epoch is instead len(dataset) items drawn with
    replacement in proportion to them, with the same seeding, so weighted runs resume exactly too."""
    n = len(dataset)
    if weights is not None:
        if weights.shape != (n,) or bool((weights < 0).any()) or not float(weights.sum()) > 0:
            raise ValueError(f"batches: weights must be {n} non-negative numbers, not all zero; got shape "
                             f"{tuple(weights.shape)}")
        weights = weights.double()
    per_epoch = max(1, n // batch_size)
    epoch, skip = divmod(start_step, per_epoch)
    while True:
        g = torch.Generator().manual_seed(seed + epoch)
        drawn = torch.randperm(n, generator=g) if weights is None else torch.multinomial(weights, n, True, generator=g)
        order = drawn[skip * batch_size:].tolist()
        loader = DataLoader(Subset(dataset, order), batch_size=batch_size, shuffle=False,
                            drop_last=n >= batch_size, generator=g, num_workers=num_workers)
        yield from loader
        epoch, skip = epoch + 1, 0


def step_seed(seed: int, step: int, stream: int = 1_000_003) -> int:
    """The seed of one training step's randomness (which frames, which augmentation): a function
    of the run's seed and the step alone, so a resumed run draws what an uninterrupted one would.
    Different `stream`s give independent draws for the same step."""
    return seed * stream + step


def per_step(make: Callable[[int], T], start: int) -> Iterator[T]:
    """`make(step)` for step = start, start + 1, ...: batches drawn by step (see `step_seed`)."""
    return (make(step) for step in count(start))


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Shift each image of a (B, C, H, W) batch by up to `pad` pixels (replicate-padded), the
    DrQ augmentation that makes low-data image policies far less brittle. One gather, no loop."""
    if pad <= 0:
        return images
    b, c, h, w = images.shape
    padded = torch.nn.functional.pad(images.float(), (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,), generator=generator)
    dy = torch.randint(0, 2 * pad + 1, (b,), generator=generator)
    rows = (dy[:, None] + torch.arange(h)[None]).to(images.device)  # (B, H)
    cols = (dx[:, None] + torch.arange(w)[None]).to(images.device)  # (B, W)
    idx_r = rows[:, None, :, None].expand(b, c, h, padded.shape[-1])
    out = padded.gather(2, idx_r)
    idx_c = cols[:, None, None, :].expand(b, c, h, w)
    return out.gather(3, idx_c).to(images.dtype)
