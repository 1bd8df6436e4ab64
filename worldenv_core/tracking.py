"""Training curves in a standard tracker: TensorBoard by default (event files beside the run's
checkpoints, `tensorboard --logdir <experiment>` or `make tensorboard`), Weights & Biases in
offline mode (`logger=wandb`; `wandb sync` uploads later), or nothing (`logger=none`).

Every training stage logs the same entries it keeps in its history (running means of losses
every `log_every` steps; post_train_loop's per-iteration reward, KL, real success and the
imagined-vs-real gap), so the tracker, the `losses.png` plot and the manifest agree.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

from omegaconf import DictConfig

from worldenv_core.errors import ConfigError
from worldenv_core.distributed import is_main

log = logging.getLogger(__name__)
LOGGERS = ("tensorboard", "wandb", "none")


class Tracker:
    """The `none` tracker, and the interface: `log(values, step)` for scalars, `close()`."""

    name = "none"

    def log(self, values: dict, step: int, group: str = "train") -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> "Tracker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def scalars(values: dict, group: str) -> dict[str, float]:
    """`group/key` -> value for the finite numbers of an entry (not its step; no strings or lists)."""
    out = {}
    for k, v in values.items():
        if k == "step" or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            continue
        out[f"{group}/{k}"] = float(v)
    return out


class TensorBoardTracker(Tracker):
    name = "tensorboard"

    def __init__(self, log_dir: Path, flush_secs: int = 10):
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = Path(log_dir)
        self.writer = SummaryWriter(str(self.log_dir), flush_secs=flush_secs)

    def log(self, values: dict, step: int, group: str = "train") -> None:
        for tag, v in scalars(values, group).items():
            self.writer.add_scalar(tag, v, step)

    def close(self) -> None:
        self.writer.close()


class WandbTracker(Tracker):
    name = "wandb"

    def __init__(self, run_dir: Path, run_id: str, run_name: str, project: str, group: str, mode: str, config: dict):
        try:
            import wandb
        except ImportError as e:
            raise ConfigError("logger=wandb needs the wandb package: pip install -e '.[wandb]' "
                              "(or use logger=tensorboard)") from e
        os.environ.setdefault("WANDB_SILENT", "true")
        run_dir.mkdir(parents=True, exist_ok=True)
        # The run id is the work dir's: a resumed training continues the same wandb run.
        self.run = wandb.init(project=project, group=group, name=run_name, id=run_id, resume="allow",
                              dir=str(run_dir), mode=mode, config=config)

    def log(self, values: dict, step: int, group: str = "train") -> None:
        self.run.log(scalars(values, group), step=step)

    def close(self) -> None:
        self.run.finish()


def make_tracker(spec: DictConfig | None, work: Path, stage: str, group: str = "", config: dict | None = None) -> Tracker:
    """The tracker a stage's `logger` setting selects (`spec`: its config node, None for none),
    writing under the run's work dir (so a resumed run appends to its own curves and an
    experiment's runs are found by `tensorboard --logdir <experiment>`). `group`: the task name
    (a wandb group). Ranks other than 0 of a torchrun launch log nothing."""
    name = spec.name if spec is not None and is_main() else "none"
    work = Path(work)
    if name == "tensorboard":
        return TensorBoardTracker(work / "tensorboard", int(spec.get("flush_secs", 10)))
    if name == "wandb":
        return WandbTracker(work, run_id=f"{stage}-{work.name}"[:64], run_name=f"{stage}/{work.name[:8]}",
                            project=spec.project, group=group, mode=spec.mode, config=config or {})
    return Tracker()
