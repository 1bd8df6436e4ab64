"""The robot drawn by the real renderer over the world model's frames (`imagination.robot_layer`).

Why: the robot is fully determined by its joint angles, yet every world model trained here smears the arm into
a ghost within 16-48 imagined steps (docs/notebook/imagined_route.md), and its imagined frames are fed back as
the next chunk's context, so the smear compounds; the reward model then fires on a smeared arm over the
target (the imagined successes after an empty grasp). The joint angles are tracked through imagination from
the imagined end-effector states (`kinematics.arm.track`, within 0.42 mm median of the recorded skeleton), so
the real scene renderer can draw the arm exactly: each chunk's last frame (what the policy reads next) gets the
robot's pixels from a MuJoCo render of the context's scene with the arm at its tracked joints and the fingers
at the imagined gripper opening, everything else from the world model; the composited frame is encoded back
into the model's latent history, so the next chunk starts from a sharp arm. Objects stay the world model's:
whether the bowl came along is still its prediction.

The scene is the context's recorded MuJoCo state (its episode's seed rebuilds the fixtures' placement), so
objects occlude the robot where they stood at the context; a moved object's occlusion is the world model's
to get right. Costs two renders of one camera per rollout per chunk, no physics step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldenv_core.kinematics.arm import SerialArm, track_rollouts
from worldenv_core.robot import FINGER_GAP_MAX

ROBOT_BODIES = ("robot0_", "gripper0_", "mount0_")  # robosuite's names for the arm, its gripper and its mount


@dataclass
class Scene:
    """Where a context's real scene is: its episode's seed (the fixtures' placement) and the MuJoCo state."""
    task_id: int
    seed: int
    sim_state: np.ndarray


class RobotLayer:
    """Renders each rollout's robot at its tracked joints in its context's scene; `composite` pastes it over
    imagined frames. One LIBERO env per task, built on first use."""

    def __init__(self, suite: str, camera: str, image_size: int):
        self.suite, self.camera, self.image_size = suite, camera, int(image_size)
        self._envs: dict[int, tuple[object, np.ndarray, SerialArm]] = {}  # task -> (env, robot geom ids, arm)
        # (task, seed) -> the fixtures' poses a reset by that seed placed (model.body_pos, body_quat): a hard reset
        # costs 3-4 s, so each seed's is done once and its placement put back for every draw
        self._fixtures: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.scenes: list[Scene] = []
        self.joints: torch.Tensor | None = None  # (B, 7)

    def _env(self, task_id: int, seed: int):
        from worldenv_core.envs.libero_env import LiberoEnv

        if task_id not in self._envs:
            env = LiberoEnv(self.suite, task_id, cameras=[self.camera], image_size=self.image_size)
            if not self._envs:  # after robosuite's own exit hook (registered with the first GL context): ours runs
                import atexit  # first, so the contexts are freed while EGL is still up (after, each one raises)

                atexit.register(self.close)
            frame = env.reset(seed=seed)
            model = env.sim.model
            self._fixtures[(task_id, seed)] = (model.body_pos.copy(), model.body_quat.copy())
            robot = np.array([g for g in range(model.ngeom)
                              if (model.body_id2name(model.geom_bodyid[g]) or "").startswith(ROBOT_BODIES)])
            self._envs[task_id] = (env, robot, SerialArm.from_env(env, frame))
        return self._envs[task_id]

    def reset(self, scenes: list[Scene], joints: torch.Tensor) -> None:
        """Each rollout's scene and its arm's joint angles (B, 7) at the context."""
        if len(scenes) != len(joints):
            raise ValueError(f"{len(scenes)} scenes for {len(joints)} rollouts' joint angles")
        self.scenes = list(scenes)
        self.joints = joints.detach().to("cpu", torch.float64)

    def advance(self, states: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The chunk's imagined end-effector states (B, K, 7) -> the joints tracked onto them, and the robot
        at the last state: rgb (B, H, W, 3) uint8 and its pixels (B, H, W) bool."""
        arms = [self._env(s.task_id, s.seed)[2] for s in self.scenes]
        joints = track_rollouts(arms, self.joints, states.detach().to("cpu", torch.float64))
        self.joints = joints[:, -1]
        opening = states[:, -1, 6].detach().to("cpu", torch.float64).clamp(0, 1).numpy()
        rgb = np.empty((len(self.scenes), self.image_size, self.image_size, 3), np.uint8)
        mask = np.empty((len(self.scenes), self.image_size, self.image_size), bool)
        for b, scene in enumerate(self.scenes):
            rgb[b], mask[b] = self._draw(scene, self.joints[b].numpy(), float(opening[b]))
        return rgb, mask

    def _draw(self, scene: Scene, joints: np.ndarray, opening: float) -> tuple[np.ndarray, np.ndarray]:
        import mujoco

        env, robot, _ = self._env(scene.task_id, scene.seed)
        key = (scene.task_id, scene.seed)
        if key not in self._fixtures:  # the fixtures' placement follows the seed, not the MuJoCo state
            env.reset(seed=scene.seed)  # a hard reset: a new MjSim (the same model, so the same geom ids)
            self._fixtures[key] = (env.sim.model.body_pos.copy(), env.sim.model.body_quat.copy())
        sim, bot = env.sim, env.raw.robots[0]
        sim.model.body_pos[:], sim.model.body_quat[:] = self._fixtures[key]
        env.set_sim_state(scene.sim_state)
        sim.data.qpos[bot._ref_joint_pos_indexes] = joints
        sim.data.qpos[bot._ref_gripper_joint_pos_indexes] = [opening * FINGER_GAP_MAX / 2, -opening * FINGER_GAP_MAX / 2]
        rgb = env.render([self.camera])[self.camera]  # forwards the new pose first
        seg = sim.render(width=self.image_size, height=self.image_size, camera_name=self.camera, segmentation=True)
        seg = seg[::-1]  # upright, as `render`
        return rgb, (seg[..., 0] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 1], robot)

    def close(self) -> None:
        for env, _, _ in self._envs.values():
            env.close()
        self._envs.clear()


def composite(frames: torch.Tensor, rgb: np.ndarray, mask: np.ndarray) -> torch.Tensor:
    """frames (B, 3, H, W) uint8 imagined; the robot's rgb (B, H, W, 3) and pixels (B, H, W) -> (B, 3, H, W) uint8."""
    robot = torch.from_numpy(rgb).permute(0, 3, 1, 2).to(frames.device)
    keep = torch.from_numpy(mask)[:, None].to(frames.device)
    return torch.where(keep, robot, frames)
