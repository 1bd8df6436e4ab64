"""A reset's scene kept, and put back without rebuilding the simulator.

Why: a LIBERO reset is a robosuite *hard* reset: the task's XML is recompiled, a new MjSim and its render
context are built (2.7-4 s of a ~9 s real RL episode on one core), although a seed always draws the same scene
(`libero_env.SCENE_SAMPLING`). The real route resets to the same few starts many times (every ES member meets
every context of its iteration: 16 resets per start), so a worker keeps what a hard reset made and puts it back
with a soft reset, bit for bit: the MuJoCo state, the fixtures' placement (model.body_pos / body_quat, sampled at
reset), and the Python-side state a hard reset rebuilds but a soft one keeps: the arm controller's arrays (its
mass matrix is read before the reset's last forward pass), the gripper's smoothed command, and the observables'
sampling clocks (robosuite 1.4). `tests/worldenv_core/envs/test_scenes.py` holds a restored scene's renders and
success equal to a fresh hard reset's over an episode prefix, and its physics and proprioception equal to float64's
last bits (on some CPUs one velocity differs by ~1e-18 after the first step, with every input found equal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_SCALARS = (np.ndarray, float, int, bool, np.floating, np.integer)


def _copy(v):
    return v.copy() if isinstance(v, np.ndarray) else v


@dataclass(frozen=True)
class Scene:
    """What a hard reset left: the flat MuJoCo state, the fixtures' poses, and the Python-side state."""

    state: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    controllers: tuple[dict, ...]
    observables: dict[str, dict]


def snapshot(control_env) -> Scene:
    """The scene `control_env` (LIBERO's ControlEnv wrapper) is in, right after a reset."""
    raw = control_env.env
    model = raw.sim.model
    return Scene(
        state=np.asarray(control_env.get_sim_state()).copy(),
        body_pos=model.body_pos.copy(), body_quat=model.body_quat.copy(),
        controllers=tuple({k: v.copy() for k, v in vars(r.controller).items() if isinstance(v, np.ndarray)}
                          for r in raw.robots),
        observables={name: {k: _copy(v) for k, v in vars(o).items() if isinstance(v, _SCALARS)}
                     for name, o in raw._observables.items()})


def restore(control_env, scene: Scene, seed: int) -> dict:
    """Put `control_env` in `scene` with a soft reset (no model rebuilt). -> the observations."""
    raw = control_env.env
    control_env.seed(int(seed))  # the soft reset's own draws are overwritten below, but stay repeatable
    hard, raw.hard_reset = raw.hard_reset, False
    try:
        control_env.reset()  # the robots, controllers and observables reset; the scene re-drawn, then replaced
    finally:
        raw.hard_reset = hard
    raw.sim.model.body_pos[:] = scene.body_pos
    raw.sim.model.body_quat[:] = scene.body_quat
    control_env.set_init_state(scene.state)
    for robot, arrays in zip(raw.robots, scene.controllers):
        qpos = raw.sim.data.qpos[robot._ref_joint_pos_indexes].copy()
        nominal, robot.init_qpos = robot.init_qpos, qpos  # the controller built at the scene's arm pose
        try:
            robot.reset(deterministic=True)
        finally:
            robot.init_qpos = nominal
        for k, v in arrays.items():
            setattr(robot.controller, k, v.copy())
        if getattr(robot, "has_gripper", False):  # a new gripper model starts from no command
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
    obs = control_env.set_init_state(scene.state)
    for name, fields in scene.observables.items():
        for k, v in fields.items():
            setattr(raw._observables[name], k, _copy(v))
    return obs


@dataclass(frozen=True)
class Moment:
    """A point inside an episode (a keyframe the real route starts from again and again): its scene as `snapshot`
    keeps it, and what a step changes that a scene does not hold: the gripper's smoothed command, the arm
    controller's scalars (its `new_update` flag decides whether the next step re-reads the model), the env's clock
    and the last observations (the proprioception a policy reads there)."""

    scene: Scene
    seed: int
    grippers: tuple[np.ndarray, ...]
    controller_scalars: tuple[dict, ...]
    clock: tuple[int, float]
    obs: dict


def moment(control_env, obs: dict, seed: int) -> Moment:
    """The point `control_env` is at, inside an episode whose scene was drawn from `seed`."""
    raw = control_env.env
    return Moment(
        scene=snapshot(control_env), seed=int(seed),
        grippers=tuple(r.gripper.current_action.copy() for r in raw.robots if getattr(r, "has_gripper", False)),
        controller_scalars=tuple({k: v for k, v in vars(r.controller).items() if isinstance(v, (bool, int, float))}
                                 for r in raw.robots),
        clock=(raw.timestep, raw.cur_time),
        obs={k: _copy(v) for k, v in obs.items()})


def back_to(control_env, kept: Moment) -> dict:
    """Put `control_env` back at `kept` with a soft reset (no model rebuilt, no steps replayed). -> its observations.
    Continuing from it is continuing from the original point to ~1e-6 of the state after 24 steps
    (`tests/worldenv_core/envs/test_scenes.py`); two continuations from the same moment are equal bit for bit."""
    raw = control_env.env
    restore(control_env, kept.scene, kept.seed)
    grippers = iter(kept.grippers)
    for robot, scalars in zip(raw.robots, kept.controller_scalars):
        if getattr(robot, "has_gripper", False):
            robot.gripper.current_action = next(grippers).copy()
        for k, v in scalars.items():
            setattr(robot.controller, k, v)
    raw.timestep, raw.cur_time = kept.clock
    return {k: _copy(v) for k, v in kept.obs.items()}
