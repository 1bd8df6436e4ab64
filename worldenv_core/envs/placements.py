"""Fresh placements: starts drawn from LIBERO's own placement sampler, never a benchmark init state.

The benchmark tests 50 fixed init states per task; a policy post-trained from only a handful of
demo starts learns those starts (on libero_object the training contexts' success rose
0.53 -> 0.68 while the benchmark did not move). A fresh placement is a reset with no init state:
LIBERO's placement sampler puts the objects (and the fixtures) where its region sampler draws them
from the reset's seed, and the arm starts with the benchmark's joint noise (`ARM_START_NOISE`), so
RL can see as many distinct starts as it has groups.

Disjoint from the evaluation by construction and by check: the seeds come from their own
namespace (one per purpose: training contexts, the validation set), and `restore` measures every
placement against the task's 50 benchmark init states, refusing one that lies within
`SAME_STATE` of any of them (measured distances are centimetres; the check proves what the
continuous sampler makes near certain).
"""

from __future__ import annotations

import numpy as np

from worldenv_core.envs.tasks import init_states, suite_seed_id

# Seed namespaces: the first word of each placement's SeedSequence (collection and evaluation seeds
# are drawn elsewhere and never start with these words).
PURPOSES = {"train": 0x7041_0001, "validation": 0x7041_0002}
# Two MuJoCo positions closer than this (max abs difference over qpos, metres / radians) are one start.
SAME_STATE = 1e-4


class BenchmarkOverlap(ValueError):
    """A fresh placement coincides with one of the benchmark's evaluation init states."""


def placement_seed(purpose: str, suite_id: int, task_id: int, index: int) -> int:
    """A well-mixed 31-bit reset seed for placement `index` of a task, stable across runs and workers."""
    if purpose not in PURPOSES:
        raise ValueError(f"placement purpose must be one of {sorted(PURPOSES)}, got {purpose!r}")
    seq = np.random.SeedSequence([PURPOSES[purpose], int(suite_id), int(task_id), int(index)])
    return int(seq.generate_state(1)[0] & 0x7FFF_FFFF)


def placement_seeds(suite: str, task_ids: list[int], count: int, purpose: str, first: int = 0) -> list[tuple[int, int]]:
    """(task id, reset seed) of `count` fresh placements spread evenly over `task_ids` (round robin:
    placement k is of task task_ids[k % len]), numbered from `first` so that consecutive calls (one
    per RL iteration) never repeat one. `replay.placement_starts` makes them starts."""
    if not task_ids:
        raise ValueError("fresh placements need at least one task id")
    out = []
    for k in range(first, first + count):
        task = task_ids[k % len(task_ids)]
        out.append((task, placement_seed(purpose, suite_seed_id(suite), task, k // len(task_ids))))
    return out


def benchmark_distance(suite: str, task_id: int, sim_state: np.ndarray, nq: int) -> float:
    """Max abs qpos difference between a flat MuJoCo state ([time, qpos, qvel]) and the nearest of
    the task's benchmark init states."""
    bench = init_states(suite, task_id)[:, 1:1 + nq]
    return float(np.abs(bench - np.asarray(sim_state)[1:1 + nq]).max(axis=1).min())


def check_not_benchmark(suite: str, task_id: int, sim_state: np.ndarray, nq: int, seed: int) -> float:
    """The placement's distance to the benchmark's init states; `BenchmarkOverlap` if it is one of them."""
    gap = benchmark_distance(suite, task_id, sim_state, nq)
    if gap < SAME_STATE:
        raise BenchmarkOverlap(f"the fresh placement of task {task_id} from seed {seed} is a benchmark init state "
                               f"(qpos within {gap:.2g}): it cannot be a training or validation start")
    return gap


def reset_placement(env, seed: int):
    """Reset `env` (a `LiberoEnv`) to the fresh placement drawn from `seed`, checked against the
    task's benchmark init states. -> its first frame."""
    frame = env.reset(init_state=None, seed=seed)
    check_not_benchmark(env.task.suite, env.task.task_id, frame.sim_state, env.sim.model.nq, seed)
    return frame
