"""Collection jobs that worker processes run: one job = one episode file (or one task's expert
evaluation). Jobs are plain picklable dataclasses so the local pool and Ray run the same code.

Resume: an episode's file name and every seed it uses are functions of the job alone, and files
appear only when complete (written to a temporary name, then renamed), so a restarted run skips
the files that exist and reproduces the rest exactly.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worldenv_core.contract import TaskContract
from worldenv_core.envs.recording import attempt_seed, cached_env, expert_attempt, to_episode
from worldenv_core.envs.placements import reset_placement


@dataclass(frozen=True)
class ExpertEpisodeJob:
    contract: TaskContract  # suite, cameras, image size, step limit, frame rate
    task_id: int
    index: int  # demo number within the task
    path: str
    seed: int
    init_mode: str  # "sampled" | "benchmark"
    max_attempts: int
    post_success_steps: int = 0  # keep acting this many steps after success (frames of the task done)


def collect_expert_episode(job: ExpertEpisodeJob) -> dict:
    """Try the expert until it succeeds (at most `max_attempts`), render and write the kept episode."""
    from worldenv_core.data.mcap_io import write_episode

    c = job.contract
    out = {"suite": c.suite, "task_id": job.task_id, "index": job.index, "path": job.path}
    if Path(job.path).exists():
        return {**out, "status": "exists"}
    t0 = time.perf_counter()
    env = cached_env(c.suite, job.task_id, c.cameras, c.image_size, render=True)
    build_s = time.perf_counter() - t0
    errors, steps_tried = [], 0
    for attempt in range(job.max_attempts):
        seed = attempt_seed(job.seed, c.suite, job.task_id, job.index, attempt)
        init = None if job.init_mode == "sampled" else job.index % 50
        traj = expert_attempt(env, init, seed, c.max_steps, post_success_steps=job.post_success_steps)
        steps_tried += traj.length
        if traj.error:
            errors.append(traj.error)
        if not traj.reached_success:  # with post_success_steps the expert may undo it afterwards: still a demo
            continue
        t_render = time.perf_counter()
        episode = to_episode(
            env, traj, init_state_index=-1 if init is None else init, seed=seed, source="expert",
            attempts=attempt + 1, fps=c.control_freq,
        )
        render_s = time.perf_counter() - t_render
        write_episode(job.path, episode)
        return {**out, "status": "kept", "attempts": attempt + 1, "frames": traj.length + 1,
                "steps_simulated": steps_tried, "render_s": render_s, "build_s": build_s,
                "seconds": time.perf_counter() - t0, "errors": errors}
    return {**out, "status": "failed", "attempts": job.max_attempts, "steps_simulated": steps_tried,
            "build_s": build_s, "seconds": time.perf_counter() - t0, "errors": errors}


@dataclass(frozen=True)
class ExpertEvalJob:
    contract: TaskContract
    task_id: int
    init_ids: tuple[int, ...]
    seed: int


def evaluate_expert_task(job: ExpertEvalJob) -> list[dict]:
    """Expert success on the benchmark's fixed init states of one task (physics only)."""
    suite = job.contract.suite
    env = cached_env(suite, job.task_id, (), 0, render=False)
    rows = []
    for i in job.init_ids:
        t0 = time.perf_counter()
        # The seeds the expert's development measurements used, so the table reproduces them.
        rng = np.random.default_rng([job.seed, job.task_id, i])
        traj = expert_attempt(env, i, job.seed * 100003 + job.task_id * 1009 + i, job.contract.max_steps, rng=rng)
        rows.append({"suite": suite, "task_id": job.task_id, "task": env.task.name, "init_state": i,
                     "success": traj.success, "steps": traj.length, "error": traj.error,
                     "seconds": time.perf_counter() - t0})
    return rows


def summarise_expert_eval(rows: list[dict]) -> list[dict]:
    """Per-task success rate and mean steps of successful episodes."""
    table = []
    for tid in sorted({r["task_id"] for r in rows}):
        rs = [r for r in rows if r["task_id"] == tid]
        ok = [r for r in rs if r["success"]]
        table.append({"task_id": tid, "task": rs[0]["task"], "n": len(rs), "successes": len(ok),
                      "success_rate": len(ok) / len(rs),
                      "mean_steps": float(np.mean([r["steps"] for r in ok])) if ok else float("nan")})
    return table


# -- policy rollouts (collect source=policy, evaluate) ----------------------------------------------
_RUNNERS: dict = {}


def cached_runner(policy_path: str, sample: bool, noise_scale: float, contract: TaskContract):
    """One loaded policy per worker process (loading costs more than an episode's first chunk)."""
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.models.policy import PolicyRunner

    key = (policy_path, sample, noise_scale)
    if key not in _RUNNERS:
        model, _ = load_checkpoint(policy_path, "policy", contract)
        _RUNNERS.clear()
        _RUNNERS[key] = PolicyRunner(model, sample=sample, noise_scale=noise_scale)
    return _RUNNERS[key]


@dataclass(frozen=True)
class PolicyEpisodeJob:
    """One Laplace-perturbed policy rollout, kept whatever its outcome."""

    policy_path: str
    contract: TaskContract
    task_id: int
    index: int
    path: str
    seed: int
    init_mode: str
    noise_scale: float
    stop_on_success: bool
    post_success_steps: int = 0


def collect_policy_episode(job: PolicyEpisodeJob) -> dict:
    from worldenv_core.data.mcap_io import write_episode
    from worldenv_core.envs.recording import policy_episode

    c = job.contract
    out = {"suite": c.suite, "task_id": job.task_id, "index": job.index, "path": job.path}
    if Path(job.path).exists():
        return {**out, "status": "exists"}
    t0 = time.perf_counter()
    env = cached_env(c.suite, job.task_id, c.cameras, c.image_size, render=True)
    runner = cached_runner(job.policy_path, True, job.noise_scale, c)
    seed = attempt_seed(job.seed, c.suite, job.task_id, job.index, 0)
    runner.generator.manual_seed(seed)  # the Laplace noise of this episode depends on the job alone
    init = None if job.init_mode == "sampled" else job.index % 50
    traj = policy_episode(env, runner, init, seed, c.max_steps, stop_on_success=job.stop_on_success,
                          post_success_steps=job.post_success_steps)
    if not traj.frames or traj.length == 0:
        return {**out, "status": "failed", "errors": [traj.error], "seconds": time.perf_counter() - t0}
    episode = to_episode(env, traj, init_state_index=-1 if init is None else init, seed=seed, source="policy",
                         fps=c.control_freq, extra={"policy": job.policy_path, "noise_scale": str(job.noise_scale),
                                             **({"error": traj.error} if traj.error else {})})
    write_episode(job.path, episode)
    return {**out, "status": "kept", "success": traj.success or bool(episode.success.any()),
            "frames": traj.length + 1, "attempts": 1, "seconds": time.perf_counter() - t0,
            "errors": [traj.error] if traj.error else []}


@dataclass(frozen=True)
class PolicyEvalJob:
    policy_path: str
    contract: TaskContract  # evaluating on another suite: `contract.on_suite(...)`
    task_id: int
    init_ids: tuple[int, ...]
    termination: str  # "oracle": stop at the first success; "fixed": run max_steps, judge the last frame;
    #                   "reflector": stop when the reflector's R > eta, judge the frame it stopped at;
    #                   "all": run max_steps with the reflector watching, rows for all three
    video_ids: tuple[int, ...] = ()
    reflector_path: str | None = None
    eta: float | None = None  # the reflector's threshold (termination reflector / all)
    view_through: str | None = None  # a world model checkpoint: the policy is shown `view_parts` of the real
    #                                  episode as that model would show them (`imagination.view`); None: as they are
    view_parts: tuple[str, ...] = ("frames", "proprio")
    placements: tuple[int, ...] = ()  # fresh placements' reset seeds (`envs.placements`), after the init states


_REFLECTORS: dict = {}


def cached_reflector(path: str, contract: TaskContract):
    from worldenv_core.models.checkpoint import load_checkpoint

    if path not in _REFLECTORS:
        _REFLECTORS.clear()
        _REFLECTORS[path] = load_checkpoint(path, "reflector", contract)[0]
    return _REFLECTORS[path]


def evaluate_policy_task(job: PolicyEvalJob) -> dict:
    """Success of the policy's mean actions from benchmark init states; videos for `video_ids`.
    termination="all" runs each episode to the horizon once, the reflector watching, and returns
    rows for oracle, fixed and reflector termination read off that one rollout."""
    from worldenv_core.envs.recording import policy_episode
    from worldenv_core.rl.termination import ReflectorStop
    from worldenv_core.rl.termination import episode_outcomes
    from worldenv_core.viz import video_picks

    c = job.contract
    env = cached_env(c.suite, job.task_id, c.cameras, c.image_size, render=True)
    runner = cached_runner(job.policy_path, False, 1.0, c)
    if job.view_through is not None:
        from worldenv_core.imagination.view import world_model_view

        runner = world_model_view(runner, job.view_through, job.task_id, c, job.view_parts)
    watch = job.termination == "all"
    reflector = cached_reflector(job.reflector_path, c) if job.termination in ("reflector", "all") else None
    rows, videos = [], {}
    starts = [(i, None) for i in job.init_ids] + [(-1, seed) for seed in job.placements]
    for i, placement in starts:
        t0 = time.perf_counter()
        if job.view_through is not None:
            runner.new_episode()
        stop = ReflectorStop(reflector, job.eta, env.instruction, runner.encoder, watch=watch) if reflector else None
        begin = None if placement is None else functools.partial(reset_placement, env, placement)
        traj = policy_episode(env, runner, i, 0, c.max_steps, stop_on_success=job.termination == "oracle",
                              stop_when=stop, start=begin)
        flags = [f.success for f in traj.frames] or [False]
        scores = stop.scores if stop is not None else []
        checks = [k * c.chunk for k in range(len(scores))]  # asked at every chunk boundary from step 0
        modes = episode_outcomes(flags, checks, scores, job.eta)
        base = {"suite": c.suite, "task_id": job.task_id, "task": env.task.name, "init_state": i,
                **({"placement_seed": placement} if placement is not None else {}),
                "ever_succeeded": bool(any(flags)), "first_success_step": flags.index(True) if any(flags) else None,
                "error": traj.error, "seconds": time.perf_counter() - t0}
        episode = []
        for mode in (("oracle", "fixed", "reflector") if watch else (job.termination,)):
            # a single-mode episode ended where that mode stops, so its last frame is judged
            m = modes[mode] if watch else {**modes["fixed"], "stop_step": modes["reflector"]["stop_step"]}
            episode.append({**base, "termination": mode, "success": traj.error is None and m["success"],
                            "steps": m["steps"], "stop_step": m["stop_step"] if mode == "reflector" else None,
                            **({"reflector_scores": [round(x, 4) for x in scores]} if mode == "reflector" else {})})
        rows += episode
        if i in job.video_ids and traj.frames:
            # only the frames the GIFs play (each mode's episode, resampled to a montage's length): frame
            # index -> image; a frame the policy saw live is not redrawn
            shown = sorted({int(j) for r in episode for j in video_picks(r["steps"] + 1)})
            states = np.stack([traj.frames[j].sim_state for j in shown])
            known = {k: traj.images[j] for k, j in enumerate(shown) if j in traj.images}
            videos[i] = dict(zip(shown, env.render_states(states, [c.cameras[0]], known=known)[c.cameras[0]]))
    return {"rows": rows, "videos": videos}
