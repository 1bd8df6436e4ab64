"""The Panda's links, for action maps that draw the whole arm and not only the gripper.

The world model is conditioned on the end-effector state drawn into the image. A disc at the grip
site leaves the model to infer where the rest of the arm is, and open loop it loses it: the arm
dissolves within 8-16 imagined steps while the gripper's disc stays. The arm's pose is fully
determined by its 7 joint angles, so the links can be drawn too:

* `SerialArm`: the chain from the robot's base to the grip site as fixed offsets and revolute
  axes, read once from the simulator's own model (`from_chain`) and stored with a world model
  (`to_dict`), so imagination needs no simulator. `points(q)` gives the skeleton the map draws.
* `track(...)`: imagination knows the end-effector states its kinematic model predicts, not the
  joints. The OSC controller moves the joints through the Jacobian toward the commanded pose;
  `track` takes the same minimal joint motion from the last known joints, one damped
  least-squares step per state, so the drawn links follow the imagined gripper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldenv_core.kinematics.next_state import axis_angle_to_matrix

ARM_JOINTS = 7
# the frames on the path from the base to the grip site (robosuite's Panda in LIBERO's scenes)
PATH = ("robot0_base", "robot0_link0", "robot0_link1", "robot0_link2", "robot0_link3", "robot0_link4",
        "robot0_link5", "robot0_link6", "robot0_link7", "robot0_right_hand", "gripper0_right_gripper",
        "gripper0_eef", "gripper0_grip_site")
# the skeleton the action map draws: the base, shoulder, elbow (two origins), forearm, wrist, hand, fingers
SKELETON = ("robot0_link0", "robot0_link1", "robot0_link3", "robot0_link4", "robot0_link5", "robot0_link7",
            "robot0_right_hand", "gripper0_grip_site")
# each skeleton segment's radius in metres (the Panda's links are 12-16 cm thick, the hand 8 cm);
# chosen against the simulator's segmentation of the robot (tests/worldenv_core/kinematics/test_arm.py)
SEGMENT_RADIUS_M = (0.08, 0.07, 0.065, 0.065, 0.06, 0.055, 0.04)


def _rotation(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """axis (3,) unit, angle (...,) -> (..., 3, 3)."""
    return axis_angle_to_matrix(angle[..., None] * axis)


@dataclass
class SerialArm:
    offsets: np.ndarray  # (F, 4, 4) each frame's fixed transform from its parent (the first: from the world)
    axes: np.ndarray  # (F, 3) the revolute axis in the frame; zeros for a fixed frame
    joints: np.ndarray  # (F,) int, which of the 7 arm joints turns the frame; -1 for fixed
    skeleton: np.ndarray  # (P,) frame indices whose origins the map joins with segments
    eef: int  # the grip site's frame index (robosuite's robot0_eef_pos)
    state_rotation: np.ndarray  # (3, 3) the proprio state's orientation in the grip site's frame

    @classmethod
    def from_chain(cls, chain) -> SerialArm:
        """From a `PandaChain` (pytorch-kinematics, built from the scene's compiled MJCF)."""
        frames = {}
        stack = [chain.chain._root]
        while stack:
            f = stack.pop()
            frames[f.name] = f
            stack.extend(f.children)
        missing = [n for n in PATH if n not in frames]
        if missing:
            raise ValueError(f"the robot's chain has no frames {missing}: not robosuite's Panda")
        names = chain.chain.get_joint_parameter_names()
        offsets, axes, joints = [], [], []
        for name in PATH:
            f = frames[name]
            m = torch.eye(4, dtype=torch.float64)
            for part in (f.link.offset, f.joint.offset):
                if part is not None:
                    m = m @ part.get_matrix()[0].to(torch.float64)
            offsets.append(m.numpy())
            revolute = f.joint.joint_type == "revolute"
            axes.append(f.joint.axis.to(torch.float64).numpy() if revolute else np.zeros(3))
            joints.append(names.index(f.joint.name) if revolute else -1)
        if sorted(j for j in joints if j >= 0) != list(range(ARM_JOINTS)):
            raise ValueError(f"the path to the grip site turns joints {joints}, not the arm's 7")
        return cls(np.stack(offsets), np.stack(axes), np.asarray(joints), np.asarray([PATH.index(n) for n in SKELETON]),
                   PATH.index("gripper0_grip_site"), np.eye(3))

    @classmethod
    def from_env(cls, env, frame) -> SerialArm:
        """From a `LiberoEnv` and one of its `Frame`s (after a reset): the chain, and the constant
        rotation between the grip site and the proprio state's orientation (robosuite reports the
        hand's quaternion, a quarter turn about z from the site)."""
        from worldenv_core.kinematics.chain import PandaChain

        arm = cls.from_chain(PandaChain.from_env(env))
        _, site = arm.eef_pose(torch.as_tensor(frame.joint_pos, dtype=torch.float64))
        state = axis_angle_to_matrix(torch.as_tensor(frame.proprio[3:6], dtype=torch.float64))
        arm.state_rotation = (site.transpose(-1, -2) @ state).numpy()
        return arm

    def to_dict(self) -> dict:
        return {"offsets": self.offsets.tolist(), "axes": self.axes.tolist(), "joints": self.joints.tolist(),
                "skeleton": self.skeleton.tolist(), "eef": int(self.eef), "state_rotation": self.state_rotation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> SerialArm:
        return cls(np.asarray(d["offsets"], dtype=np.float64), np.asarray(d["axes"], dtype=np.float64),
                   np.asarray(d["joints"], dtype=np.int64), np.asarray(d["skeleton"], dtype=np.int64), int(d["eef"]),
                   np.asarray(d["state_rotation"], dtype=np.float64))

    def transforms(self, q: torch.Tensor) -> torch.Tensor:
        """q (..., 7) -> (..., F, 4, 4) every frame's world transform."""
        q = q.to(torch.float64)
        offsets = torch.as_tensor(self.offsets, device=q.device)
        axes = torch.as_tensor(self.axes, device=q.device)
        t = offsets[0].expand(*q.shape[:-1], 4, 4)
        out = [t]
        for i in range(1, len(self.offsets)):
            t = t @ offsets[i]
            if self.joints[i] >= 0:
                turn = torch.zeros(*q.shape[:-1], 4, 4, dtype=q.dtype, device=q.device)
                turn[..., :3, :3] = _rotation(axes[i], q[..., int(self.joints[i])])
                turn[..., 3, 3] = 1.0
                t = t @ turn
            out.append(t)
        return torch.stack(out, dim=-3)

    def points(self, q: torch.Tensor) -> torch.Tensor:
        """q (..., 7) -> (..., P, 3) the skeleton's world points (base to hand)."""
        return self.transforms(q)[..., self.skeleton, :3, 3]

    def eef_pose(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q (..., 7) -> the grip site's world position (..., 3) and rotation (..., 3, 3)."""
        t = self.transforms(q)[..., self.eef, :, :]
        return t[..., :3, 3], t[..., :3, :3]

    def site_rotation(self, state_rotation: torch.Tensor) -> torch.Tensor:
        """(..., 3, 3) a proprio state's orientation -> the grip site's."""
        return state_rotation @ torch.as_tensor(self.state_rotation, dtype=state_rotation.dtype,
                                                device=state_rotation.device).transpose(-1, -2)

    def jacobian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """q (B, 7) -> the grip site's geometric Jacobian (B, 6, 7) (linear rows, then angular), its
        position (B, 3) and rotation (B, 3, 3)."""
        t = self.transforms(q)
        pe = t[:, self.eef, :3, 3]
        jac = torch.zeros(q.shape[0], 6, ARM_JOINTS, dtype=torch.float64, device=q.device)
        axes = torch.as_tensor(self.axes, device=q.device)
        for i, j in enumerate(self.joints):
            if j >= 0:
                z = t[:, i, :3, :3] @ axes[i]
                jac[:, :3, j] = torch.linalg.cross(z, pe - t[:, i, :3, 3])
                jac[:, 3:, j] = z
        return jac, pe, t[:, self.eef, :3, :3]


def _rotation_error(target: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) x 2 -> (B, 3) the world-frame rotation vector taking `current` to `target`."""
    from pytorch_kinematics.transforms import matrix_to_axis_angle

    return matrix_to_axis_angle(target @ current.transpose(-1, -2))


def track(arm: SerialArm, joints: torch.Tensor, states: torch.Tensor, damping: float = 1e-4) -> torch.Tensor:
    """joints (B, 7) the arm's last known joint angles, states (B, n, 7) the end-effector states that
    follow (position, axis-angle, gripper) -> (B, n, 7) joint angles, one per state: a damped
    least-squares step from the previous angles onto each state's pose (the minimal joint motion).
    Measured on 10 libero_spatial demos tracked from their first frame (10,920 steps): the skeleton
    lands within 0.42 mm (median), 13 mm (90th percentile) and 50 mm (worst) of the recorded joints'
    (`python -m analysis.arm_maps`); pulling toward a rest posture in the nullspace, as OSC's torque
    law does, made it worse (p90 11-60 mm at gains 0.05-0.2 on four episodes)."""
    q = joints.to(torch.float64)
    targets = states.to(q)
    out = []
    for k in range(targets.shape[1]):
        pos, rot = targets[:, k, :3], arm.site_rotation(axis_angle_to_matrix(targets[:, k, 3:6]))
        jac, pe, re = arm.jacobian(q)
        err = torch.cat([pos - pe, _rotation_error(rot, re)], dim=-1)
        jjt = jac @ jac.transpose(1, 2) + damping * torch.eye(6, dtype=q.dtype, device=q.device)
        q = q + (jac.transpose(1, 2) @ torch.linalg.solve(jjt, err[..., None]))[..., 0]
        out.append(q)
    return torch.stack(out, dim=1)


def rollout_groups(items: list) -> list[tuple[object, list[int]]]:
    """A batch's rollouts grouped by the object each sees (its scene's camera or arm), in first-seen order:
    one batched computation per distinct object."""
    groups: dict[int, tuple[object, list[int]]] = {}
    for i, item in enumerate(items):
        groups.setdefault(id(item), (item, []))[1].append(i)
    return list(groups.values())


def skeletons(joints: torch.Tensor, arms: list[SerialArm]) -> torch.Tensor:
    """joints (B, ..., 7), arms[b] rollout b's arm -> (B, ..., P, 3) the skeletons to draw."""
    if len(arms) != joints.shape[0]:
        raise ValueError(f"{len(arms)} arms for a batch of {joints.shape[0]} rollouts")
    out = torch.empty(*joints.shape[:-1], len(SKELETON), 3, dtype=torch.float64, device=joints.device)
    for arm, idx in rollout_groups(arms):
        out[idx] = arm.points(joints[idx])
    return out


def track_rollouts(arms: list[SerialArm], joints: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """`track` for a batch whose rollouts may see different arms: joints (B, 7), states (B, n, 7) -> (B, n, 7)."""
    out = torch.empty(*states.shape[:-1], ARM_JOINTS, dtype=torch.float64, device=states.device)
    for arm, idx in rollout_groups(arms):
        out[idx] = track(arm, joints[idx], states[idx])
    return out
