"""One factory for every LIBERO suite: the real benchmark env, reused across episodes.

Rendering is the dominant cost of the simulator (STACK.md: ~13 ms per physics step against
~100 ms per 128 px camera render), so the env never renders on `step`; callers ask for images
with `render()` exactly where they keep them (every frame of a kept demo, every chunk boundary
of a policy). `render=False` refuses `render()` (LIBERO's env still builds a GL context for it).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from worldenv_core.envs.scenes import Moment, Scene, back_to, moment, snapshot
from worldenv_core.envs.scenes import restore as restore_scene
from worldenv_core.envs.substeps import SplitSubsteps
from worldenv_core.envs.tasks import TaskSpec, get_task, init_states
from worldenv_core.robot import ACTION_DIM, gripper_opening

os.environ.setdefault("MUJOCO_GL", "egl")
log = logging.getLogger(__name__)

# The arm's start on a sampled reset: robosuite's "default" initialization noise, Gaussian with this
# standard deviation (rad) on each joint. LIBERO's benchmark init states were made with it (in
# libero_object tasks 0 and 1 their joints spread by 0.016-0.021 rad about the nominal pose); LIBERO's
# own env turns it off, so without it every demo would start from one pose no benchmark episode starts from.
ARM_START_NOISE = 0.02
# How a reset draws its scene, for caches of results that depend on it. 2: every reset draws the scene a
# freshly built env's first reset draws from the same seed (`LiberoEnv.reset`); 1 (before): a scene also
# depended on how often the env had been reset.
SCENE_SAMPLING = 2


class SimulationError(RuntimeError):
    """The physics became unstable (NaN state, MuJoCo warning turned error) during an episode."""


@dataclass
class Frame:
    """What the env reports about one instant. `images` is empty unless rendered."""

    proprio: np.ndarray  # (7,) eef pos, eef axis-angle, gripper opening in [0, 1]
    joint_pos: np.ndarray  # (7,)
    sim_state: np.ndarray  # flattened MuJoCo state
    success: bool
    images: dict[str, np.ndarray] = field(default_factory=dict)


def quat_xyzw_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """robosuite's convention: xyzw quaternion -> rotation vector (angle in [0, pi])."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q)
    if q[3] < 0:  # pick the hemisphere with a non-negative scalar part: angle <= pi
        q = -q
    sin_half = np.linalg.norm(q[:3])
    if sin_half < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(sin_half, q[3])
    return q[:3] / sin_half * angle


def proprio_from_obs(obs: dict) -> np.ndarray:
    """The paper's s_t = (eef position 3, eef axis-angle 3, gripper opening 1)."""
    qpos = obs["robot0_gripper_qpos"]
    opening = gripper_opening(qpos[0], qpos[1])
    return np.concatenate(
        [obs["robot0_eef_pos"], quat_xyzw_to_axis_angle(obs["robot0_eef_quat"]), [opening]]
    ).astype(np.float32)


class LiberoEnv:
    """A LIBERO task in robosuite, built once and reset many times.

    Args:
        suite, task_id: which benchmark task.
        cameras: cameras `render()` returns by default (e.g. agentview, robot0_eye_in_hand).
        image_size: square render resolution in pixels.
        render: False builds a physics-only env (no offscreen renderer), for work that keeps no images.
        arm_start_noise: std (rad) of the joint noise of a sampled reset (`ARM_START_NOISE`, as the
            benchmark's); 0 starts every sampled episode from the one nominal pose. An init state
            restores the joints it recorded either way.
        scene_cache: keep the scenes of this many recent fresh-placement resets (by seed) and put one
            back without rebuilding the simulator when it comes again (`scenes.py`: the same physics and
            renders as a hard reset, ~0.04 s instead of ~3 s); 0: every reset is a hard reset.
    """

    def __init__(self, suite: str, task_id: int, cameras=("agentview",), image_size: int = 128, render: bool = True,
                 arm_start_noise: float = ARM_START_NOISE, scene_cache: int = 0):
        if not arm_start_noise >= 0:
            raise ValueError(f"arm_start_noise must be >= 0 (rad), got {arm_start_noise}")
        self.task: TaskSpec = get_task(suite, task_id)
        self.cameras = list(cameras)
        self.image_size = int(image_size)
        self.can_render = bool(render)
        from libero.libero.envs import OffScreenRenderEnv

        with contextlib.redirect_stdout(io.StringIO()):
            self._env = OffScreenRenderEnv(
                bddl_file_name=self.task.bddl_path,
                has_offscreen_renderer=self.can_render,
                use_camera_obs=False,  # we render by hand, only the frames we keep
                camera_names=self.cameras or ["agentview"],
                camera_heights=self.image_size,
                camera_widths=self.image_size,
                ignore_done=True,  # the episode length is ours to decide, not robosuite's horizon
                initialization_noise={"magnitude": float(arm_start_noise), "type": "gaussian"},
            )
        self._obs: dict | None = None
        # LIBERO appends a task's open/close and on/off samplers (a drawer's, a stove's) to this list at every
        # model load and never clears it, so each hard reset drew one more set from the seeded RNG than the one
        # before: the fixtures' and objects' placement of a seed moved (by ~2 cm) with the env's reset count.
        self._property_samplers = len(getattr(self._env.env, "object_property_initializers", []))
        self._scenes: OrderedDict[int, Scene] = OrderedDict()  # fresh placements' scenes, by seed
        self._scene_cache = int(scene_cache)
        self.restored = False  # whether the last reset put a kept scene back instead of rebuilding it
        self._moments: OrderedDict[str, tuple[Moment, object]] = OrderedDict()  # points inside episodes (`keep_moment`), by key
        self._seed = 0  # the last reset's: a kept moment's scene is redrawn from it

    # -- properties -------------------------------------------------------------------------
    @property
    def raw(self):
        """The libero ControlEnv (privileged access for scripted experts)."""
        return self._env

    @property
    def sim(self):
        return self._env.sim

    @property
    def instruction(self) -> str:
        return self.task.instruction

    @property
    def max_steps(self) -> int:
        return self.task.max_steps

    # -- episode control ----------------------------------------------------------------------
    def reset(self, init_state: int | np.ndarray | None = None, seed: int | None = None, hard: bool = False) -> Frame:
        """Reset to a benchmark init state (an index or a flat MuJoCo state), or, with
        `init_state=None`, to a fresh random placement drawn from `seed`. `hard`: rebuild the scene even where one is
        kept (and keep the new one).

        The seed matters in both cases: LIBERO's reset re-samples the *fixtures'* placement
        (cabinets, stoves: model.body_pos) and the arm's start from numpy's global RNG, and an init state restores
        only qpos/qvel, so an unseeded reset is not reproducible. `seed=None` means seed 0. With a
        `scene_cache`, a placement seen before is put back from its kept scene (bit for bit the same)."""
        seed = self._seed = int(seed) if seed is not None else 0
        # fresh placements only: a benchmark init state set over a sampled reset came back ~1e-17 apart after a
        # step (MuJoCo's solver scratch differs between a reused and a new MjData), and each is reset once anyway
        key = seed if self._scene_cache and init_state is None else None
        self.restored = key is not None and key in self._scenes and not hard
        if self.restored:
            self._scenes.move_to_end(key)
            self._obs = restore_scene(self._env, self._scenes[key], seed)
            return self.observe()
        self._free_gl()  # a hard reset rebuilds the render context: the old one goes in its own context
        self._env.seed(seed)
        samplers = getattr(self._env.env, "object_property_initializers", None)
        if samplers is not None:  # as after construction: this reset draws what a fresh env's first one draws
            del samplers[self._property_samplers:]
        self._obs = self._env.reset()
        if init_state is not None:
            if isinstance(init_state, (int, np.integer)):
                states = init_states(self.task.suite, self.task.task_id)
                if not 0 <= int(init_state) < len(states):
                    raise IndexError(f"init state {init_state} out of range 0..{len(states) - 1} for {self.task.name}")
                init_state = states[int(init_state)]
            self._obs = self._env.set_init_state(np.asarray(init_state))
        if key is not None:
            self._scenes[key] = snapshot(self._env)
            while len(self._scenes) > self._scene_cache:
                self._scenes.popitem(last=False)
        return self.observe()

    def keep_moment(self, key: str, info=None) -> None:
        """Keep the point this env is at under `key` (with a `scene_cache`, as many of the recent ones): a keyframe the
        real route starts from again (ES members from the same recorded frame) comes back with `back_to` in ~0.1 s
        instead of a reset and the recorded actions replayed to it (4-6 s at mid-task). `info` comes back with it."""
        if self._scene_cache:
            self._moments[key] = moment(self._env, self._obs, self._seed), info
            while len(self._moments) > self._scene_cache:
                self._moments.popitem(last=False)

    def back_to(self, key: str) -> tuple[Frame, object] | None:
        """The env put back at the point kept under `key` (`keep_moment`) and its `info`, or None where none is kept."""
        if key not in self._moments:
            return None
        self._moments.move_to_end(key)
        kept, info = self._moments[key]
        self._obs = back_to(self._env, kept)
        return self.observe(), info

    def step(self, action: np.ndarray) -> Frame:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action has non-finite entries: {action}")
        with SplitSubsteps(self._env.env):  # one pass of MuJoCo's stages per physics substep (substeps.py)
            self._obs, _, _, _ = self._env.step(np.clip(action, -1.0, 1.0))
        frame = self.observe()
        if not np.all(np.isfinite(frame.sim_state)):
            raise SimulationError(f"non-finite MuJoCo state in {self.task.name}")
        return frame

    def observe(self, render: bool = False) -> Frame:
        obs = self._obs
        return Frame(
            proprio=proprio_from_obs(obs),
            joint_pos=np.asarray(obs["robot0_joint_pos"], dtype=np.float64).copy(),
            sim_state=self._env.get_sim_state().astype(np.float64).copy(),
            success=bool(self._env.check_success()),
            images=self.render() if render else {},
        )

    def check_success(self) -> bool:
        return bool(self._env.check_success())

    # -- rendering and replay -------------------------------------------------------------------
    def render(self, cameras=None) -> dict[str, np.ndarray]:
        """Upright uint8 images of the current state (robosuite renders upside down)."""
        if not self.can_render:
            raise RuntimeError("this env was built with render=False (physics only)")
        # mj_step leaves body poses one substep behind the state it reports; forward() syncs
        # them so a live render equals a render replayed from the recorded state, bit for bit.
        self.sim.forward()
        self._gl_current()
        out = {}
        for cam in cameras or self.cameras:
            img = self.sim.render(width=self.image_size, height=self.image_size, camera_name=cam)
            out[cam] = np.ascontiguousarray(img[::-1])
        return out

    def set_sim_state(self, flat_state: np.ndarray) -> None:
        """Put the simulator in a recorded state (replaying a physics-only episode to render it)."""
        self._env.set_state(np.asarray(flat_state, dtype=np.float64))
        self.sim.forward()

    def render_states(self, states: np.ndarray, cameras=None, known: dict | None = None) -> dict[str, np.ndarray]:
        """Render a recorded sequence of MuJoCo states: camera -> (T, H, W, 3) uint8.

        known: frame index -> camera -> image already rendered live at that state (a policy's chunk boundaries,
        about one frame in eight); a live render equals the replayed one bit for bit, so those are not redrawn."""
        cams = list(cameras or self.cameras)
        known = known or {}
        frames: dict[str, list] = {c: [] for c in cams}
        for t, s in enumerate(states):
            have = known.get(t, {})
            missing = [c for c in cams if c not in have]
            if missing:
                self.set_sim_state(s)
                have = {**have, **self.render(missing)}
            for cam in cams:
                frames[cam].append(have[cam])
        return {c: np.stack(v) for c, v in frames.items()}

    # robosuite makes a GL context current only when it builds one, and frees one (at a hard reset, at
    # close, or later at garbage collection) in whichever context is current. With several envs in one
    # process (a worker's cached envs), an env would render its poses with another model's meshes and
    # textures, and freeing one would delete another's GL objects of the same ids, silently.
    def _gl_current(self):
        """Make this env's GL context current (LIBERO builds one even with render=False); -> its render context."""
        ctx = getattr(self.sim, "_render_context_offscreen", None)
        if ctx is not None:
            ctx.gl_ctx.make_current()
        return ctx

    def _free_gl(self) -> None:
        """Free this env's GL objects in its own context; robosuite's own free, later, is then a no-op."""
        ctx = self._gl_current()
        if ctx is not None:
            ctx.con.free()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._free_gl()
            self._env.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
