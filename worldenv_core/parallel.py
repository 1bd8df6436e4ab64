"""Run independent jobs (episodes) in parallel: in-process, on local worker processes, or on Ray.

Every launcher takes the same top-level function and list of picklable jobs and yields results
as they complete, so stages write one loop with one progress bar whatever runs the work.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from tqdm import tqdm

from worldenv_core.errors import raise_if_stopped

log = logging.getLogger(__name__)
LAUNCHERS = ("local", "ray")


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def _die_with_parent(parent_pid: int | None) -> None:
    """Linux: the kernel kills this worker when the process that started it dies (even by
    SIGKILL), so no orphan goes on writing episodes after its parent is gone."""
    if parent_pid is None or not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:  # the parent died before the line above took effect
        os._exit(1)


def limit_threads(threads: int) -> None:
    """Cap this process's OpenMP / MKL / torch threads (the variables for libraries not yet loaded)."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    os.environ.setdefault("MKL_NUM_THREADS", str(threads))
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass


def _init_worker(parent_pid: int | None = None) -> None:
    _die_with_parent(parent_pid)
    # Ctrl-C reaches the whole process group: the parent alone handles it (one line, the pool torn
    # down with it), instead of every worker printing its own traceback.
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Episodes are the unit of parallelism; nested BLAS/torch threads would only fight over cores.
    limit_threads(1)


def _validate(launcher: str, workers: int | None) -> int:
    if launcher not in LAUNCHERS:
        raise ValueError(f"unknown launcher {launcher!r}; valid launchers: {', '.join(LAUNCHERS)}")
    if workers is None:
        return default_workers()
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1 (or null for all cores), got {workers}")
    return int(workers)


def run_jobs(
    fn: Callable[[Any], Any],
    jobs: Iterable[Any],
    workers: int | None = None,
    launcher: str = "local",
    desc: str = "jobs",
    ray_address: str | None = None,
    progress: bool = True,
    unit: str = "ep",
) -> Iterator[Any]:
    """Yield `fn(job)` for every job, in completion order, with a progress bar."""
    jobs = list(jobs)
    workers = _validate(launcher, workers)
    bar = tqdm(total=len(jobs), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)
    try:
        if launcher == "ray":
            results = _ray_results(fn, jobs, workers, ray_address)
        elif workers == 1 or len(jobs) <= 1:
            results = (fn(j) for j in jobs)
        else:
            results = _pool_results(fn, jobs, workers)
        for done, r in enumerate(results, 1):
            bar.update(1)
            yield r
            raise_if_stopped(f"after {done} of {len(jobs)} {desc}")  # before the next job: see errors.request_stop
    finally:
        bar.close()


def _pool_results(fn, jobs, workers) -> Iterator[Any]:
    # spawn, not fork: MuJoCo/EGL contexts and torch threads do not survive a fork safely.
    ctx = mp.get_context("spawn")
    with ctx.Pool(processes=min(workers, len(jobs)), initializer=_init_worker, initargs=(os.getpid(),),
                  maxtasksperchild=None) as pool:
        yield from pool.imap_unordered(fn, jobs, chunksize=1)


def _ray_results(fn, jobs, workers, address) -> Iterator[Any]:
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        # address=None starts a local Ray instance; "auto" or "ray://host:port" joins a cluster.
        # A local instance's workers at the driver's priority: Ray starts them at niceness 15, so on a
        # busy machine they get a few per cent of a core (the collect stage's Ray test: 23 s alone,
        # 460 s in the test suite); the jobs are the work, the driver only waits for them.
        local = {"_system_config": {"worker_niceness": 0}} if address is None else {}
        ray.init(address=address, num_cpus=workers if address is None else None,
                 include_dashboard=False, log_to_driver=False, ignore_reinit_error=True, **local)
    try:
        remote = ray.remote(num_cpus=1)(_ray_call)
        pending = [remote.remote(fn, j) for j in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started_here:
            ray.shutdown()


def _ray_call(fn, job):
    _init_worker()
    return fn(job)
