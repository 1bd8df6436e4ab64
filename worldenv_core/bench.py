"""`make bench`: what the real simulator costs on this machine, measured side by side.

Prints medians over repeats (shared machines are noisy): env build, one physics-only step,
one camera render, and the throughput of expert collection (kept frames per second).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from worldenv_core.envs.libero_env import LiberoEnv
from worldenv_core.envs.recording import attempt_seed, expert_attempt, to_episode


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def simulator_costs(suite: str, task_id: int, image_size: int, cameras: list[str], repeats: int) -> dict:
    t0 = time.perf_counter()
    env = LiberoEnv(suite, task_id, cameras=cameras, image_size=image_size)
    build_s = time.perf_counter() - t0
    env.reset(init_state=0)
    rng = np.random.default_rng(0)
    step_ms = statistics.median(
        _median_ms(lambda: env.step(np.r_[rng.uniform(-0.3, 0.3, 6), -1.0]), 20) for _ in range(repeats))
    render_ms = _median_ms(env.render, 10 * repeats)
    # Expert collection: physics-only attempts, then render the kept ones by replaying states.
    episodes = []
    for i in range(repeats):
        t0 = time.perf_counter()
        traj = expert_attempt(env, None, attempt_seed(0, suite, task_id, i, 0), env.max_steps)
        if traj.success:
            to_episode(env, traj, init_state_index=-1, seed=0, source="expert")
        episodes.append({"frames": traj.length + 1, "success": traj.success, "s": time.perf_counter() - t0})
    kept = [e for e in episodes if e["success"]]
    env.close()
    return {
        "suite": suite, "task_id": task_id, "image_size": image_size, "cameras": cameras,
        "env_build_s": round(build_s, 2),
        "physics_step_ms_median": round(step_ms, 2),
        "render_ms_per_frame_median": round(render_ms, 1),
        "expert_success": f"{len(kept)}/{len(episodes)}",
        "kept_frames_per_s_median": round(statistics.median(e["frames"] / e["s"] for e in kept), 2) if kept else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--suite", default="libero_object")
    parser.add_argument("--task-id", type=int, default=0)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--cameras", nargs="+", default=["agentview"])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    result = simulator_costs(args.suite, args.task_id, args.image_size, args.cameras, args.repeats)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
