"""The task contract (diffusion_policy's `shape_meta`): what `conf/task/*.yaml` promises every
component, as one object built once per run. Data, policy, world simulator, reflector and the
real environment read shapes and limits from it; every checkpoint carries `contract.meta()` and
a loader calls `contract.check(meta)`, so a model made for other shapes is a clear error, never a
silent reshape."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

# What a checkpoint must agree on with the run that loads it. Suite and task may differ on
# purpose (a policy trained on libero_goal evaluated on libero_goal_swap).
SHAPE_KEYS = ("image_size", "chunk", "action_dim", "proprio_dim")


class ContractError(ValueError):
    """A checkpoint or input made for another task contract."""


@dataclass(frozen=True)
class TaskContract:
    name: str  # the task config's name (tiny, libero_goal, ...): what artefacts are tagged with
    suite: str
    task_ids: tuple[int, ...] | None  # None: every task of the suite
    cameras: tuple[str, ...]
    image_size: int
    chunk: int
    action_dim: int
    proprio_dim: int
    max_steps: int
    control_freq: float

    @classmethod
    def from_config(cls, task) -> "TaskContract":
        """From a validated `cfg.task` (`stage.require_task` fills a null max_steps first)."""
        ids = task.get("task_ids")
        return cls(name=str(task.name), suite=str(task.suite), task_ids=None if ids is None else tuple(int(t) for t in ids),
                   cameras=tuple(str(c) for c in task.cameras), image_size=int(task.image_size), chunk=int(task.chunk),
                   action_dim=int(task.action_dim), proprio_dim=int(task.proprio_dim), max_steps=int(task.max_steps),
                   control_freq=float(task.control_freq))

    def on_suite(self, suite: str, max_steps: int) -> "TaskContract":
        """The same shapes on another registered suite with the same task ids (LIBERO-PRO variants),
        at that suite's step limit (`envs.tasks.suite_max_steps`: the caller looks it up, so the
        contract depends on nothing above it)."""
        return dataclasses.replace(self, suite=suite, max_steps=int(max_steps))

    def meta(self) -> dict:
        """What every checkpoint records of the contract it was trained under."""
        return {"task": self.name, "suite": self.suite, **{k: getattr(self, k) for k in SHAPE_KEYS}}

    def check(self, meta: dict, where: str) -> None:
        """`meta` (a checkpoint's) agrees with this contract on every shape it records. A policy
        also records the cameras it looks through (a world model and a reflector record the one
        camera they watch, checked where they are paired)."""
        for key in SHAPE_KEYS:
            if key in meta and meta[key] != getattr(self, key):
                raise ContractError(f"{where} was made for {key}={meta[key]!r}, but this run's task contract "
                                    f"({self.name}) has {key}={getattr(self, key)!r}")
        if isinstance(meta.get("cameras"), list) and meta["cameras"] != list(self.cameras):
            raise ContractError(f"{where} looks through cameras {meta['cameras']}, but this run's task contract "
                                f"({self.name}) has {list(self.cameras)}")
