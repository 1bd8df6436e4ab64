"""Record episodes in the real simulator: act without cameras, keep the MuJoCo state per step,
and render only the episodes that are kept, by replaying their states (as robomimic does). A policy's
chunk-boundary frames, rendered live for it to act on, are kept and not replayed (one render in eight saved).

A failed expert attempt therefore costs physics only (~10 ms per step), never rendering.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from worldenv_core.envs.libero_env import Frame, LiberoEnv
from worldenv_core.envs.tasks import suite_seed_id
from worldenv_core.errors import raise_if_stopped

log = logging.getLogger(__name__)

# Per-process cache: building a LIBERO env costs seconds (a sampled reset rebuilds its model too, but not the
# process-level setup).
_ENV_CACHE: "OrderedDict[tuple, LiberoEnv]" = OrderedDict()
_ENV_CACHE_SIZE = 2
# fresh placements a cached env keeps to put back without a hard reset (`LiberoEnv(scene_cache=)`): the real
# route's ES iteration meets each of its 16 starts once per member, a worker its share of them
SCENE_CACHE = 64


def cached_env(suite: str, task_id: int, cameras, image_size: int, render: bool = True) -> LiberoEnv:
    key = (suite, int(task_id), tuple(cameras), int(image_size), bool(render))
    env = _ENV_CACHE.pop(key, None)
    if env is None:
        env = LiberoEnv(suite, task_id, cameras=cameras, image_size=image_size, render=render, scene_cache=SCENE_CACHE)
    _ENV_CACHE[key] = env
    while len(_ENV_CACHE) > _ENV_CACHE_SIZE:
        _ENV_CACHE.popitem(last=False)[1].close()
    return env


def attempt_seed(base_seed: int, suite: str, task_id: int, episode_index: int, attempt: int) -> int:
    """A well-mixed 32-bit seed per attempt, stable across runs and workers (resume relies on it)."""
    seq = np.random.SeedSequence([int(base_seed), suite_seed_id(suite), int(task_id), int(episode_index), int(attempt)])
    return int(seq.generate_state(1)[0])


@dataclass
class Trajectory:
    """A physics-only rollout: T+1 frames (no images yet) and T actions."""

    frames: list[Frame]
    actions: list[np.ndarray]
    step_extras: dict[str, list[np.ndarray]] = field(default_factory=dict)
    error: str | None = None  # set when the simulator failed mid-episode
    # frame index -> camera -> image rendered live (a policy's chunk boundaries): kept, they need no replay
    images: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.error is None and bool(self.frames) and self.frames[-1].success

    @property
    def reached_success(self) -> bool:
        """The oracle fired at some frame (what a demo must show; frames after it may undo it)."""
        return self.error is None and any(f.success for f in self.frames)

    @property
    def length(self) -> int:
        return len(self.actions)


def rollout(
    env: LiberoEnv,
    act: Callable[[Frame, int], np.ndarray | tuple[np.ndarray, dict]],
    first: Frame,
    max_steps: int,
    stop_on_success: bool = True,
    finished: Callable[[], bool] = lambda: False,
    post_success_steps: int = 0,
) -> Trajectory:
    """Step `act(frame, t)` until success (and `post_success_steps` more: frames showing the task
    done, which the reflector learns from), `finished()`, or `max_steps`. `act` may also return
    (action, extras) so a policy can log its mu/beta per step. A simulator exception ends the
    episode as failed with the error recorded; it never propagates to kill a collection run."""
    traj = Trajectory(frames=[first], actions=[])
    frame = first
    success_at = None
    try:
        for t in range(max_steps):
            raise_if_stopped()  # a stop whose interrupt LIBERO's bare excepts swallowed ends the episode here
            if success_at is None and frame.success:
                success_at = t
            if success_at is not None and stop_on_success and t - success_at >= post_success_steps:
                break
            if (success_at is None or not stop_on_success) and finished():
                break
            out = act(frame, t)
            action, extras = out if isinstance(out, tuple) else (out, {})
            frame = env.step(action)
            traj.actions.append(np.asarray(action, dtype=np.float32))
            for k, v in extras.items():
                traj.step_extras.setdefault(k, []).append(np.asarray(v, dtype=np.float32))
            traj.frames.append(frame)
    except Exception as e:  # noqa: BLE001 - any physics failure marks this episode failed
        traj.error = f"{type(e).__name__}: {e}"
        log.warning("episode failed in %s at step %d: %s\n%s", env.task.name, len(traj.actions), traj.error,
                    traceback.format_exc(limit=3))
    return traj


def expert_attempt(env: LiberoEnv, init_state, seed: int, max_steps: int,
                   rng: np.random.Generator | None = None, post_success_steps: int = 0) -> Trajectory:
    """One scripted-expert attempt from a benchmark init state (index) or a seeded placement (None).
    `seed` fixes the scene; `rng` (default: seeded from `seed`) the expert's own jitter."""
    from worldenv_core.envs.expert import ScriptedExpert

    try:
        first = env.reset(init_state=init_state, seed=seed)
        expert = ScriptedExpert(env.raw, rng if rng is not None else np.random.default_rng(seed))
    except Exception as e:  # noqa: BLE001
        return Trajectory(frames=[], actions=[], error=f"reset failed: {type(e).__name__}: {e}")
    return rollout(env, lambda frame, t: expert.act(), first, max_steps, finished=lambda: expert.finished,
                   post_success_steps=post_success_steps)


def to_episode(env: LiberoEnv, traj: Trajectory, **meta):
    """Render the kept trajectory by replaying its states and package it as an Episode."""
    from worldenv_core.data.episode import Episode, EpisodeMeta

    states = np.stack([f.sim_state for f in traj.frames])
    images = env.render_states(states, known=traj.images)
    meta.setdefault("cameras", list(env.cameras))
    return Episode(
        meta=EpisodeMeta(
            suite=env.task.suite, task_id=env.task.task_id, task_name=env.task.name,
            instruction=env.task.instruction, success=traj.reached_success, **meta,
        ),
        images=images,
        proprio=np.stack([f.proprio for f in traj.frames]).astype(np.float32),
        joint_pos=np.stack([f.joint_pos for f in traj.frames]).astype(np.float64),
        sim_state=states.astype(np.float64),
        success=np.array([f.success for f in traj.frames], dtype=bool),
        actions=np.stack(traj.actions).astype(np.float32) if traj.actions else np.zeros((0, 7), np.float32),
        step_extras={k: np.stack(v) for k, v in traj.step_extras.items()},
    )


class Timer:
    def __init__(self):
        self.t0 = time.perf_counter()

    def __call__(self) -> float:
        return time.perf_counter() - self.t0


def policy_episode(env: LiberoEnv, runner, init_state, seed: int, max_steps: int,
                   stop_on_success: bool = True, post_success_steps: int = 0, stop_when=None,
                   start: Callable[[], Frame] | None = None) -> Trajectory:
    """Run a policy (a `PolicyRunner`) chunk by chunk, rendering the cameras it sees only at chunk
    boundaries, and logging its mu/beta for every executed action.

    stop_when: optional callable (camera -> (H, W, 3) image) -> bool asked at every chunk boundary
    (a reflector's dynamic termination, see `ReflectorStop`); its `cameras` are rendered too.
    start: puts the env where the episode begins (default: reset to `init_state` with `seed`),
    e.g. `envs.replay.restore` for a frame in the middle of a recorded episode."""
    try:
        first = start() if start is not None else env.reset(init_state=init_state, seed=seed)
    except Exception as e:  # noqa: BLE001
        return Trajectory(frames=[], actions=[], error=f"reset failed: {type(e).__name__}: {e}")
    queue: list = []
    cameras = list(dict.fromkeys([*runner.cameras, *(stop_when.cameras if stop_when else [])]))
    rendered: dict = {}  # this boundary's images, shared by the stop check and the policy

    def boundary_images():
        if "images" not in rendered:
            rendered["images"] = env.render(cameras)
        return rendered["images"]

    live: dict[int, dict] = {}  # frame t -> its boundary images, which `to_episode` then need not render again

    def act(frame: Frame, t: int):
        if not queue:
            images = live[t] = boundary_images()
            rendered.clear()
            actions, mu, beta = runner.act_chunk(images, frame.proprio, env.instruction)
            queue.extend(zip(actions, mu, beta))
        a, m, b = queue.pop(0)
        return a, {"mu": m, "beta": b}

    def finished() -> bool:
        return stop_when is not None and not queue and bool(stop_when(boundary_images()))

    traj = rollout(env, act, first, max_steps, stop_on_success=stop_on_success, finished=finished,
                   post_success_steps=post_success_steps)
    traj.images = live
    return traj
