"""Privileged scripted expert for LIBERO, driven by the task's BDDL goal predicates.

Usage::

    env.reset(); env.set_init_state(init)
    expert = ScriptedExpert(env, np.random.default_rng(seed))
    while not expert.finished and steps < limit:
        env.step(expert.act())
    success = env.check_success()
"""
from __future__ import annotations

import numpy as np

from .context import ExpertContext
from .planner import PREDICATE_HANDLERS, plan

__all__ = ["ScriptedExpert", "ExpertContext", "PREDICATE_HANDLERS"]


class ScriptedExpert:
    """Pulls actions from the goal-driven plan generator one env step at a time."""

    def __init__(self, env, rng: np.random.Generator):
        self.ctx = ExpertContext(env=env, rng=rng)
        self._plan = plan(self.ctx)
        self._finished = False

    def act(self) -> np.ndarray:
        """Next 7-D action in [-1, 1]; a hold-still (gripper open) action once finished."""
        if not self._finished:
            try:
                a = next(self._plan)
                return np.clip(np.asarray(a, dtype=np.float64), -1.0, 1.0)
            except StopIteration:
                self._finished = True
        a = np.zeros(7, dtype=np.float64)
        a[6] = -1.0
        return a

    @property
    def finished(self) -> bool:
        return self._finished
