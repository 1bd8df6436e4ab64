"""The Panda arm as a pytorch-kinematics chain, built from the robot's own MJCF in the scene.

`PandaChain.from_env(env)` reads the model robosuite compiled for this scene (so link lengths,
the mount and the gripper are exactly the simulator's); `eef_pose(joint_pos)` gives the
grip site's world pose, batched, on any device.
"""

from __future__ import annotations

import torch

EEF_FRAME = "gripper0_grip_site"


class PandaChain:
    def __init__(self, chain, eef_frame: str = EEF_FRAME):
        self.chain = chain
        self.eef_frame = eef_frame

    @classmethod
    def from_env(cls, env) -> PandaChain:
        """`env`: a `LiberoEnv` (or its raw robosuite env)."""
        import pytorch_kinematics as pk

        raw = getattr(env, "raw", env)
        inner = getattr(raw, "env", raw)
        robot = inner.robots[0]
        # the compiled robot model carries its mount pose in the scene, so the chain's root
        # frame is already the world frame
        return cls(pk.build_chain_from_mjcf(robot.robot_model.get_xml(), body="robot0_base").to(dtype=torch.float64))

    @property
    def frames(self) -> list[str]:
        return self.chain.get_frame_names()

    def fk(self, joint_pos: torch.Tensor, frame: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """joint_pos (B, 7) arm joints -> world position (B, 3) and rotation (B, 3, 3) of `frame`
        (default: the grip site, whose position is robosuite's `robot0_eef_pos`)."""
        q = torch.as_tensor(joint_pos, dtype=torch.float64)
        q = torch.nn.functional.pad(q, (0, len(self.chain.get_joint_parameter_names()) - q.shape[-1]))  # fingers at 0
        m = self.chain.forward_kinematics(q)[frame or self.eef_frame].get_matrix()
        return m[:, :3, 3], m[:, :3, :3]
