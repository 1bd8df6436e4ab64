"""Pinhole projection with a benchmark camera's intrinsics and extrinsics read from MuJoCo.

MuJoCo cameras look down their local -z axis with +y up. Our images are upright (the env flips
robosuite's upside-down renders), so a point at camera coordinates (x, y, z), z < 0, lands at
column u = cx + f * x / -z and row v = cy - f * y / -z, with f = (H / 2) / tan(fovy / 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class PinholeCamera:
    name: str
    image_size: int
    focal: float  # pixels
    position: np.ndarray  # (3,) camera origin in the world
    rotation: np.ndarray  # (3, 3) camera-to-world rotation (columns: camera x, y, z axes)

    @classmethod
    def from_sim(cls, sim, name: str, image_size: int) -> PinholeCamera:
        """Read a camera from a robosuite MjSim (after `sim.forward()`; cameras may move with bodies)."""
        cam_id = sim.model.camera_name2id(name)
        fovy = np.deg2rad(float(sim.model.cam_fovy[cam_id]))
        return cls(name=name, image_size=int(image_size), focal=0.5 * image_size / np.tan(fovy / 2),
                   position=np.array(sim.data.cam_xpos[cam_id], dtype=np.float64),
                   rotation=np.array(sim.data.cam_xmat[cam_id], dtype=np.float64).reshape(3, 3))

    def to_dict(self) -> dict:
        return {"name": self.name, "image_size": self.image_size, "focal": float(self.focal),
                "position": self.position.tolist(), "rotation": self.rotation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> PinholeCamera:
        return cls(name=d["name"], image_size=int(d["image_size"]), focal=float(d["focal"]),
                   position=np.asarray(d["position"], dtype=np.float64),
                   rotation=np.asarray(d["rotation"], dtype=np.float64))

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points (..., 3) -> camera-frame points (..., 3)."""
        pos = torch.as_tensor(self.position, dtype=points.dtype, device=points.device)
        rot = torch.as_tensor(self.rotation, dtype=points.dtype, device=points.device)
        return (points - pos) @ rot  # R^T (p - c), written for row vectors

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (..., 3) -> pixel coordinates (..., 2) as (column u, row v) in the upright
        image, and the depth along the view direction (..., ) (positive in front of the camera)."""
        cam = self.to_camera(points)
        depth = -cam[..., 2]
        safe = depth.clamp(min=1e-6)
        c = (self.image_size - 1) / 2.0  # pixel centres: the image spans [-0.5, H - 0.5]
        u = c + self.focal * cam[..., 0] / safe
        v = c - self.focal * cam[..., 1] / safe
        return torch.stack([u, v], dim=-1), depth
