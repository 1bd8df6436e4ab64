"""Measure the scripted expert on LIBERO's fixed init states.

    python -m worldenv_core.envs.expert.evaluate --suite libero_object --n-init 10

Physics only (no cameras), one env per task reused across init states.
"""
from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict

import numpy as np

from . import ScriptedExpert

STEP_LIMITS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520,
               "libero_90": 400}


def make_env(suite_name: str, task_id: int):
    from libero.libero import benchmark, get_libero_path
    from libero.libero.envs import OffScreenRenderEnv

    suite = benchmark.get_benchmark_dict()[suite_name]()
    task = suite.get_task(task_id)
    bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
    env = OffScreenRenderEnv(bddl_file_name=bddl, has_offscreen_renderer=False, use_camera_obs=False)
    return env, task, suite.get_task_init_states(task_id)


def run_episode(env, init_state, rng: np.random.Generator, max_steps: int,
                env_seed: int | None = None) -> dict:
    """Roll the expert out until its plan is exhausted or ``max_steps``.

    Returns ``success`` (goal reached at some step within the limit, LIBERO's usual
    criterion), ``steps`` (first success step, else steps run) and ``success_at_end``
    (goal still holds when the plan is exhausted / the limit hits: what a collector that
    steps until ``expert.finished`` sees).
    """
    if env_seed is not None:
        # LIBERO's reset() re-samples *fixture* placements (model.body_pos) from the global
        # numpy RNG and set_init_state() does not restore them (it sets qpos/qvel only), so
        # seed it to make an episode reproducible.
        env.seed(env_seed)
    env.reset()
    env.set_init_state(init_state)
    expert = ScriptedExpert(env, rng)
    steps, first = 0, None
    while steps < max_steps and not expert.finished:
        env.step(expert.act())
        steps += 1
        if first is None and env.check_success():
            first = steps
    return dict(success=first is not None, steps=first if first is not None else steps,
                success_at_end=bool(env.check_success()), plan_steps=steps)


def evaluate_expert(suite: str, task_ids, init_state_ids, seed: int = 0,
                    max_steps: int | None = None, verbose: bool = False) -> list[dict]:
    """One row per (task, init state): suite, task_id, task, init, success, steps,
    success_at_end, plan_steps, seconds (see :func:`run_episode`)."""
    limit = max_steps or STEP_LIMITS.get(suite, 300)
    rows = []
    for tid in task_ids:
        env, task, inits = make_env(suite, tid)
        try:
            for i in init_state_ids:
                if i >= len(inits):
                    continue
                rng = np.random.default_rng([seed, tid, i])
                t0 = time.time()
                res = run_episode(env, inits[i], rng, limit, env_seed=seed * 100003 + tid * 1009 + i)
                row = dict(suite=suite, task_id=tid, task=task.name, init=i, **res,
                           seconds=round(time.time() - t0, 2))
                rows.append(row)
                if verbose:
                    print(row, flush=True)
        finally:
            env.close()
    return rows


def format_table(rows: list[dict]) -> str:
    by = defaultdict(list)
    for r in rows:
        by[(r["suite"], r["task_id"], r["task"])].append(r)
    lines = [f"{'suite':15s} {'id':>2s} {'n':>3s} {'succ':>4s} {'rate':>5s} {'steps':>6s} {'@end':>4s}  task"]
    tot_n = tot_s = tot_e = 0
    for (suite, tid, name), rs in sorted(by.items()):
        n, s = len(rs), sum(r["success"] for r in rs)
        ms = np.mean([r["steps"] for r in rs if r["success"]]) if s else float("nan")
        e = sum(r.get("success_at_end", r["success"]) for r in rs)
        tot_n, tot_s, tot_e = tot_n + n, tot_s + s, tot_e + e
        lines.append(f"{suite:15s} {tid:2d} {n:3d} {s:4d} {s / n:5.2f} {ms:6.1f} {e:4d}  {name}")
    if tot_n:
        lines.append(f"{'total':15s} {'':2s} {tot_n:3d} {tot_s:4d} {tot_s / tot_n:5.2f} {'':6s} {tot_e:4d}")
    lines.append("succ: goal reached within the step limit; steps: mean first-success step;"
                 " @end: goal still holds when the plan is exhausted")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--suite", default="libero_object")
    p.add_argument("--tasks", type=int, nargs="*", default=None, help="task ids (default: all)")
    p.add_argument("--n-init", type=int, default=10)
    p.add_argument("--init-start", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("-v", "--verbose", action="store_true")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    a = p.parse_args(argv)
    if a.tasks is None:
        from libero.libero import benchmark
        a.tasks = list(range(benchmark.get_benchmark_dict()[a.suite]().n_tasks))
    rows = evaluate_expert(a.suite, a.tasks, range(a.init_start, a.init_start + a.n_init), a.seed,
                           a.max_steps, a.verbose)
    print(format_table(rows))
    if a.json:
        import json

        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
