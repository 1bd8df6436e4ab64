"""Resumable training state: `<work>/checkpoints/<step:07d>/` holds the self-describing model
(`models.checkpoint`) and the training state beside it (optimizers, RNG states, the history and
any extra state such as EMA weights); `last` names the newest complete one."""

from __future__ import annotations

import logging
import random
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from worldenv_core.files import writing
from worldenv_core.models.checkpoint import load_weights, save_model

log = logging.getLogger(__name__)
TRAIN_STATE = "training_state.pt"


class Checkpoints:
    """`<work>/checkpoints/<step:07d>/` (self-describing model + training state), `last` -> newest."""

    def __init__(self, work_dir: str | Path, keep: int = 2):
        self.dir = Path(work_dir) / "checkpoints"
        self.keep = keep
        self.extra: dict = {}  # the `extra` of the checkpoint last restored
        self.trainer: dict | None = None  # its Trainer bookkeeping (None: none restored, or one written before it)

    @property
    def last(self) -> Path | None:
        link = self.dir / "last"
        return link.resolve() if link.exists() else None

    def save(self, step: int, model, model_config: dict, meta: dict, optimizers: dict, history: list[dict],
             extra: dict | None = None, trainer: dict | None = None) -> Path:
        """`extra`: more training state to restore (e.g. EMA weights), left in `self.extra` by `restore`.
        The weights and the training state are written into `<step>.staging/` and land together by
        one rename, so an interrupt or a full disk never leaves a checkpoint without its state (nor
        an empty temporary file: a failed save removes what it wrote)."""
        final = self.dir / f"{step:07d}"
        staging = final.with_name(final.name + ".staging")
        with writing(final, staging, staging.with_name(staging.name + ".tmp")):
            save_model(staging, model, model_config, {**meta, "step": step})
            state = {
                "step": step,
                "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
                "history": history,
                "extra": extra or {},
                "trainer": trainer or {},
            }
            torch.save(state, staging / TRAIN_STATE)
            if final.exists():
                shutil.rmtree(final)
            staging.rename(final)
        path = final
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
        weights = load_weights(ckpt / "model.safetensors")
        state = torch.load(ckpt / TRAIN_STATE, weights_only=False)
        model.load_state_dict(weights)
        for k, o in optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        self.extra = state.get("extra", {})
        self.trainer = state.get("trainer")
        log.info("resumed from %s (step %d)", ckpt, state["step"])
        return int(state["step"]), list(state["history"])
