"""Paired replay: the real outcome of actions chosen in imagination.

Every recorded frame carries its MuJoCo state and the simulator is deterministic, so the true
outcome of an action sequence from any context is known: put the real simulator where the
context starts and execute exactly those actions, open loop. A context starts either at a
benchmark init state or at frame t of a recorded episode. The controller's internal state (the
OSC goal, the gripper's) is not part of the MuJoCo state, so setting the state of frame t alone
makes the next step differ (measured: a joint velocity off by 1.07 from frame 40 of an expert
episode); `restore` therefore rebuilds the episode's scene from its seed and replays its recorded
actions up to t, which reproduces the recorded states (within 1e-6) and frames.

`replay_context` is a worker job (picklable, like `envs.collection`): one context, the action
sequences of all its imagined rollouts, and optionally closed-loop rollouts of the same policy,
each one real episode.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from worldenv_core.contract import TaskContract
from worldenv_core.envs.libero_env import Frame, LiberoEnv
from worldenv_core.envs.placements import placement_seeds, reset_placement
from worldenv_core.envs.recording import cached_env


@dataclass(frozen=True)
class RealStart:
    """Where a context starts in the real simulator: a benchmark init state (`episode` None,
    `init_state` >= 0), a fresh placement (`episode` None, `init_state` -1: LIBERO's placement sampler
    from `seed`, see `envs.placements`) or frame `frame` of a recorded episode (its scene rebuilt
    from its seed, its actions replayed)."""

    task_id: int
    init_state: int = -1  # benchmark init-state index; -1: the episode's own placement
    seed: int = 0
    episode: str | None = None
    frame: int = 0

    @property
    def key(self) -> str:
        """Unique among the starts of a run: a benchmark init state is one per task, so its key names the
        task (results keyed by 'init0' alone once paired every task's start with the last task's replays)."""
        if self.episode is None:
            return f"task{self.task_id}/init{self.init_state}" if self.init_state >= 0 else \
                f"task{self.task_id}/placement{self.seed}"
        return f"{self.episode}@{self.frame}"

    @property
    def placement(self) -> bool:
        """A fresh placement (no benchmark init state, no recorded episode)."""
        return self.episode is None and self.init_state < 0


def placement_starts(suite: str, task_ids: list[int], count: int, purpose: str, first: int = 0) -> list[RealStart]:
    """`count` fresh-placement starts over `task_ids` (`placements.placement_seeds`)."""
    return [RealStart(task_id=t, seed=s) for t, s in placement_seeds(suite, task_ids, count, purpose, first)]


def by_start(results) -> dict[str, dict]:
    """Replay results (`replay_context`'s, in completion order) by their start's key. Two starts of one
    run with one key would pair a context with another's replays, so a repeated key is refused."""
    out: dict[str, dict] = {}
    for r in results:
        key = r["start"].key
        if key in out:
            raise ValueError(f"two contexts start at {key}: their replays cannot be told apart")
        out[key] = r
    return out


class ReplayError(RuntimeError):
    """Replaying a recorded prefix did not reproduce the recorded state."""


@dataclass(frozen=True)
class StartJob:
    """A worker job about one context start (picklable)."""

    contract: TaskContract
    start: RealStart


def replays(job: StartJob) -> dict:
    """Whether replaying a recorded episode's prefix reaches its recorded state at the context's
    frame (a real rollout or a paired replay starts there); the error if not."""
    c = job.contract
    env = cached_env(c.suite, job.start.task_id, c.cameras, c.image_size, render=False)
    try:
        restore(env, job.start)
    except ReplayError as e:
        return {"start": job.start, "error": str(e)}
    return {"start": job.start, "error": None}


def unreplayable(contract: TaskContract, starts: list[RealStart], cache=None, **run_kw) -> dict[str, str]:
    """start key -> error, for the mid-episode starts whose recorded prefix does not replay to its
    recorded state (a few demos do not: their contact is not reproducible from the seed). Checked
    before any rollout so such a start is dropped, not met half way through a run. `cache`: a file of
    checks kept between sittings (`replay_checks.ReplayChecks`): only starts it has no valid answer for
    are replayed. `run_kw`: `run_jobs`' workers, launcher, ray_address, progress."""
    from worldenv_core.envs.replay_checks import MISSING, ReplayChecks
    from worldenv_core.parallel import run_jobs

    kept = ReplayChecks(cache)
    known = {s.key: kept.get(s) for s in starts if s.episode is not None and s.frame}
    jobs = [StartJob(contract, s) for s in starts if known.get(s.key) is MISSING]
    checks = run_jobs(replays, jobs, desc="context replays", unit="ctx", **run_kw) if jobs else []
    kept.put(checks)
    errors = {k: e for k, e in known.items() if e is not MISSING and e}
    return {**errors, **{r["start"].key: r["error"] for r in checks if r["error"]}}


def restore(env: LiberoEnv, start: RealStart, tolerance: float = 1e-3) -> Frame:
    """Put `env` at the context's start and return that frame (no images). A fresh placement is
    checked against the benchmark's init states (`placements.BenchmarkOverlap` if it is one). A recorded frame is
    replayed to once per env and kept (`LiberoEnv.keep_moment`, with a `scene_cache`): ES members meet each keyframe
    once per member, and the replay (4-6 s at mid-task) was most of a 16-step rollout's time."""
    if start.placement:
        return reset_placement(env, start.seed)
    if start.episode is None:
        return env.reset(init_state=start.init_state, seed=start.seed)
    kept = env.back_to(start.key) if start.frame else None  # a keyframe this env replayed to before
    if kept is not None:
        frame, gap = kept
    else:
        frame, gap = _replay_to(env, start)
        if gap > tolerance and env.restored:  # a kept scene put back is not the hard reset bit for bit after every
            frame, gap = _replay_to(env, start, hard=True)  # contact (measured: 0.504 at frame 187 of a rollout)
        if start.frame:
            env.keep_moment(start.key, gap)
    if gap > tolerance:
        raise ReplayError(f"replaying {start.episode} to frame {start.frame} ends {gap:.3g} away from the "
                          f"recorded state (tolerance {tolerance})")
    return frame


def _replay_to(env: LiberoEnv, start: RealStart, hard: bool = False) -> tuple[Frame, float]:
    """The recorded episode's scene reset (`hard`: rebuilt, not put back from a kept one), its first state set and its
    actions replayed to `start.frame`. -> that frame and its distance from the recorded state there."""
    from worldenv_core.data.mcap_io import read_episode

    ep = read_episode(start.episode, cameras=[])
    frame = env.reset(init_state=ep.meta.init_state_index if ep.meta.init_state_index >= 0 else None, seed=ep.meta.seed,
                      hard=hard)
    env.set_sim_state(ep.sim_state[0])
    for a in ep.actions[:start.frame]:
        frame = env.step(a)
    gap = float(np.abs(frame.sim_state - ep.sim_state[start.frame]).max()) if start.frame and ep.sim_state.shape[1] else 0.0
    return frame, gap


def execute(env: LiberoEnv, start: RealStart, actions: np.ndarray, every: int, camera: str,
            scorer=None, keep: frozenset[int] | None = None) -> dict:
    """Execute `actions` (T, 7) open loop from `start`. Every `every` steps the camera is rendered
    (what the imagined env and its reflector see); `scorer` (a reward model's incremental scorer)
    scores those frames. Returns the oracle's flags, the first success step, the scores and the
    rendered frames at the steps in `keep` (None: all of them)."""
    t0 = time.perf_counter()
    frame = restore(env, start)
    flags, frames, scores = [frame.success], {}, []

    def look(t: int) -> None:
        if scorer is None and keep is not None and t not in keep:
            return  # nobody looks at this frame: skip the render (the dominant cost)
        img = env.render([camera])[camera]
        if keep is None or t in keep:
            frames[t] = img
        if scorer is not None:
            import torch

            scorer.add(torch.from_numpy(img).permute(2, 0, 1)[None])
            scores.append(float(scorer.score()[0]))

    look(0)
    error = None
    try:
        for t, a in enumerate(actions, start=1):
            frame = env.step(a)
            flags.append(frame.success)
            if t % every == 0 or t == len(actions):
                look(t)
    except Exception as e:  # noqa: BLE001 - a physics failure is a failed replay, not a dead worker
        error = f"{type(e).__name__}: {e}"
    hits = np.flatnonzero(flags)
    return {"success": bool(len(hits)) and error is None, "first_success": int(hits[0]) if len(hits) else None,
            "success_at_end": bool(flags[-1]) and error is None, "steps": len(flags) - 1, "scores": scores,
            "frames": frames, "error": error, "seconds": time.perf_counter() - t0}


@dataclass(frozen=True)
class PairedReplayJob:
    contract: TaskContract
    start: RealStart
    actions: tuple  # one (T_i, 7) float32 array per imagined rollout
    keep: tuple  # per rollout, the steps whose real frames come back (None: every checked step)
    reflector_path: str | None = None  # score the real frames with this reflector
    # closed loop: the same policy acting on real frames from the same start, Laplace noise seeded per rollout
    policy_path: str | None = None
    closed_loop_seeds: tuple = ()
    noise_scale: float = 1.0
    horizon: int = 0


def recorded_history(start: RealStart, camera: str, every: int):
    """The recorded frames before a mid-episode start that its imagined side's reward model is shown
    (`Context.history`), (n, 3, H, W) uint8; None for a start at an episode's beginning or a placement."""
    from worldenv_core.data.mcap_io import read_episode
    from worldenv_core.imagination.env import history_frames

    if start.episode is None or start.frame < every or every <= 0:
        return None
    return history_frames(read_episode(start.episode, cameras=[camera], load_sim_state=False).images[camera],
                          start.frame, every)


@functools.cache
def _encoder():
    """One instruction encoder per worker process (loading it costs more than a replay's scoring)."""
    from worldenv_core.models.text import InstructionEncoder

    return InstructionEncoder()


def replay_context(job: PairedReplayJob) -> dict:
    """The real outcome of every imagined rollout of one context (and, with `policy_path`, of
    closed-loop rollouts of the policy from there). Each replay or rollout is one real episode."""
    from worldenv_core.envs.collection import cached_reflector, cached_runner
    from worldenv_core.envs.recording import policy_episode

    c = job.contract
    camera = c.cameras[0]
    env = cached_env(c.suite, job.start.task_id, c.cameras, c.image_size, render=True)
    reflector = cached_reflector(job.reflector_path, c) if job.reflector_path else None
    encoder = _encoder() if reflector is not None else None
    history = recorded_history(job.start, camera, c.chunk) if reflector is not None else None
    replays = []
    for actions, keep in zip(job.actions, job.keep):
        scorer = reflector.scorer([env.instruction], encoder) if reflector is not None else None
        if history is not None and hasattr(scorer, "add_history"):  # the imagined side's scorer saw the same past
            scorer.add_history([history])
        replays.append(execute(env, job.start, np.asarray(actions), c.chunk, camera, scorer,
                               None if keep is None else frozenset(keep)))
    closed = []
    if job.policy_path and job.closed_loop_seeds:
        runner = cached_runner(job.policy_path, True, job.noise_scale, c)
        for seed in job.closed_loop_seeds:
            runner.generator.manual_seed(int(seed))
            traj = policy_episode(env, runner, None, 0, job.horizon, start=lambda: restore(env, job.start))
            closed.append({"success": traj.reached_success, "steps": traj.length, "error": traj.error})
    return {"start": job.start, "replays": replays, "closed_loop": closed}
