"""What every training stage shares: the `Trainer` loop and its `Phase`s, resumable
`Checkpoints`, seeded batches that resume exactly, and data-parallel runs under torchrun
(`worldenv_core.distributed`)."""

from worldenv_core.training.batches import batches, per_step, pick_device, random_shift, step_seed
from worldenv_core.training.checkpoints import TRAIN_STATE, Checkpoints
from worldenv_core.distributed import trainer_options
from worldenv_core.training.trainer import (Phase, RunningMeans, Trainer, optimize, planned_steps, planned_total,
                                             record_checkpoint)

__all__ = ["TRAIN_STATE", "Checkpoints", "Phase", "RunningMeans", "Trainer", "batches", "optimize", "per_step",
           "pick_device", "planned_steps", "planned_total", "random_shift", "record_checkpoint", "step_seed",
           "trainer_options"]
