"""What every training stage shares: device choice, endless seeded batches, resumable
checkpoints (`<work>/checkpoints/<step>/` + `last`), and loss curves as a plot."""

from __future__ import annotations

import json
import logging
import random
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from worldenv_core.models.checkpoint import save_model

log = logging.getLogger(__name__)
TRAIN_STATE = "training_state.pt"


def pick_device(name: str = "auto") -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def batches(dataset: Dataset, batch_size: int, seed: int, start_step: int = 0, num_workers: int = 0) -> Iterator[dict]:
    """Endless shuffled batches. Epoch e is a permutation drawn with seed + e, and a run resumed at
    step s starts at batch s of that order, so it sees exactly the batches an uninterrupted run
    would (resume is bit-identical). The loader gets its own generator: creating one draws a seed,
    which must not come from the global RNG that augmentation and dropout use."""
    n = len(dataset)
    per_epoch = max(1, n // batch_size)
    epoch, skip = divmod(start_step, per_epoch)
    while True:
        g = torch.Generator().manual_seed(seed + epoch)
        order = torch.randperm(n, generator=g)[skip * batch_size:].tolist()
        loader = DataLoader(Subset(dataset, order), batch_size=batch_size, shuffle=False,
                            drop_last=n >= batch_size, generator=g, num_workers=num_workers)
        yield from loader
        epoch, skip = epoch + 1, 0


class Checkpoints:
    """`<work>/checkpoints/<step:07d>/` (self-describing model + training state), `last` -> newest."""

    def __init__(self, work_dir: str | Path, keep: int = 2):
        self.dir = Path(work_dir) / "checkpoints"
        self.keep = keep
        self.extra: dict = {}  # the `extra` of the checkpoint last restored

    @property
    def last(self) -> Path | None:
        link = self.dir / "last"
        return link.resolve() if link.exists() else None

    def save(self, step: int, model, model_config: dict, meta: dict, optimizers: dict, history: list[dict],
             extra: dict | None = None) -> Path:
        """`extra`: more training state to restore (e.g. EMA weights), left in `self.extra` by `restore`."""
        path = save_model(self.dir / f"{step:07d}", model, model_config, {**meta, "step": step})
        state = {
            "step": step,
            "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
            "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
            "history": history,
            "extra": extra or {},
        }
        torch.save(state, path / (TRAIN_STATE + ".tmp"))
        (path / (TRAIN_STATE + ".tmp")).rename(path / TRAIN_STATE)
        tmp_link = self.dir / "last.tmp"
        tmp_link.unlink(missing_ok=True)
        tmp_link.symlink_to(path.name)
        tmp_link.replace(self.dir / "last")  # atomic: `last` always names a complete checkpoint
        for old in sorted(p for p in self.dir.iterdir() if p.name.isdigit())[:-self.keep]:
            shutil.rmtree(old)
        return path

    def restore(self, model, optimizers: dict) -> tuple[int, list[dict]]:
        """Load the newest readable checkpoint into `model` and `optimizers`; (0, []) when there is
        none. A damaged one (truncated or garbled weights or state) is moved aside with a warning and
        the one before it is tried, so a re-run repairs a damaged work dir instead of failing on it."""
        candidates = sorted((p for p in self.dir.iterdir() if p.name.isdigit()), reverse=True) if self.dir.is_dir() else []
        for ckpt in candidates:
            if not (ckpt / TRAIN_STATE).exists():
                continue
            try:
                return self._load(ckpt, model, optimizers)
            except Exception as e:  # noqa: BLE001 - whatever a damaged file raises, the next one is tried
                aside = ckpt.with_name(f"{ckpt.name}.damaged-{time.strftime('%Y%m%dT%H%M%S')}")
                ckpt.rename(aside)
                log.warning("checkpoint %s is damaged (%s: %s); moved to %s, trying the one before it",
                            ckpt, type(e).__name__, str(e)[:200], aside.name)
        return 0, []

    def _load(self, ckpt: Path, model, optimizers: dict) -> tuple[int, list[dict]]:
        from worldenv_core.models.checkpoint import load_weights

        weights = load_weights(ckpt / "model.safetensors")
        state = torch.load(ckpt / TRAIN_STATE, weights_only=False)
        model.load_state_dict(weights)
        for k, o in optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        self.extra = state.get("extra", {})
        log.info("resumed from %s (step %d)", ckpt, state["step"])
        return int(state["step"]), list(state["history"])


def plot_history(history: list[dict], path: str | Path, title: str = "") -> Path:
    """One panel per logged loss/metric against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in dict.fromkeys(k for h in history for k in h) if k != "step"]  # entries may differ
    cols = min(4, max(1, len(keys)))  # a grid, not one long strip: readable at page width
    rows = -(-max(1, len(keys)) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False)
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
    path = Path(path)
    fig.savefig(path.with_suffix(".tmp.png"))
    plt.close(fig)
    path.with_suffix(".tmp.png").replace(path)
    (path.with_suffix(".json")).write_text(json.dumps(history))
    return path


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


class RunningMeans:
    """Per-step values (losses, diagnostics) averaged into one `history` entry every `every`
    steps and at the last, shown on the progress bar and sent to the tracker (TensorBoard, ...)."""

    def __init__(self, history: list[dict], every: int, bar=None, tracker=None):
        self.history, self.every, self.bar, self.tracker = history, int(every), bar, tracker
        self.values: dict[str, list[float]] = {}

    def add(self, **values: float) -> None:
        for k, v in values.items():
            self.values.setdefault(k, []).append(float(v))

    def end_step(self, done: int, total: int) -> None:
        if done % self.every and done != total:
            return
        entry = {"step": done, **{k: sum(v) / len(v) for k, v in self.values.items()}}
        self.history.append(entry)
        self.values.clear()
        if self.tracker is not None:
            self.tracker.log(entry, done)
        if self.bar is not None:
            self.bar.set_postfix({k: f"{v:.4f}" for k, v in entry.items() if k != "step"})
