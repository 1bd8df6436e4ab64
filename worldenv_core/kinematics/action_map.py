"""Action maps (EVAC, World-Env sec. 4.1): the end-effector state s_{t+1} drawn into the camera
image on a black background, as pixel conditioning for the world simulator.

A filled white disc at the projected gripper position whose radius grows with the gripper
opening, and three line segments for the gripper's x (red), y (green) and z (blue) axes.
Everything is drawn at once for a batch of states with distance fields over the pixel grid
(soft, anti-aliased edges), no Python loop over pixels or states.
"""

from __future__ import annotations

import torch

from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import axis_angle_to_matrix

AXIS_LENGTH_M = 0.10
AXIS_COLOURS = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _pixel_grid(size: int, device) -> torch.Tensor:
    """(S, S, 2) pixel centres as (u, v)."""
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")
    return torch.stack([xs, ys], dim=-1).to(device)


def _project_to(points: torch.Tensor, camera: PinholeCamera, size: int) -> torch.Tensor:
    """points (..., 3) -> their pixel positions (..., 2) in an image of `size` (the camera's own resized)."""
    uv, _ = camera.project(points)
    return (uv + 0.5) * (size / camera.image_size) - 0.5  # pixel centres at the new size


def _coverage(dist: torch.Tensor, radius: torch.Tensor | float) -> torch.Tensor:
    """Pixel coverage of a shape whose edge is at `radius` from its skeleton (1-pixel ramp)."""
    return (radius + 0.5 - dist).clamp(0.0, 1.0)


def _segment_distance(grid: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """grid (H, W, 2), a/b (..., 2) -> distance from each pixel to each segment (..., H, W)."""
    a, b = a[..., None, None, :], b[..., None, None, :]
    ab = b - a
    t = (((grid - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-9)).clamp(0.0, 1.0)
    return (grid - (a + t[..., None] * ab)).norm(dim=-1)


def draw_action_maps(states: torch.Tensor, camera: PinholeCamera, size: int | None = None,
                     radius_px: tuple[float, float] | None = None, line_px: float | None = None) -> torch.Tensor:
    """states (..., 7) = (eef pos, eef axis-angle, gripper opening in [0, 1]) ->
    maps (..., 3, S, S) in [0, 1], S = `size` (default: the camera's resolution; a world model
    that only patch-embeds its maps can take them smaller, and drawing costs S^2). Radii default
    to a fraction of the size so that maps look alike at every resolution: a disc of 2 %..5 % of
    the width, lines of 0.8 %."""
    size = int(size or camera.image_size)
    r_closed, r_open = radius_px or (0.02 * size, 0.05 * size)
    half_line = 0.5 * (line_px or max(1.0, 0.008 * size))
    lead = states.shape[:-1]
    s = states.reshape(-1, 7).to(torch.float32)
    pos, rot = s[:, :3], axis_angle_to_matrix(s[:, 3:6])
    ends = pos[:, None, :] + AXIS_LENGTH_M * rot.transpose(1, 2)  # (N, 3 axes, 3): rows = axis directions
    centre, tips = _project_to(pos, camera, size), _project_to(ends, camera, size)
    grid = _pixel_grid(size, s.device)  # (H, W, 2) as (u, v)
    radius = r_closed + (r_open - r_closed) * s[:, 6].clamp(0, 1)
    disc = _coverage((grid - centre[:, None, None, :]).norm(dim=-1), radius[:, None, None])  # (N, H, W)
    lines = _coverage(_segment_distance(grid, centre[:, None, :].expand_as(tips), tips), half_line)  # (N, 3, H, W)

    colours = torch.tensor(AXIS_COLOURS, device=s.device)  # (3 axes, 3 rgb)
    img = disc[:, None].expand(-1, 3, -1, -1).clone()  # white disc
    for axis in range(3):  # paint the three axes over the disc (3 iterations, whole batch each)
        alpha = lines[:, axis, None]
        img = img * (1 - alpha) + alpha * colours[axis][None, :, None, None]
    return img.reshape(*lead, 3, size, size)


def draw_action_maps_per_rollout(states: torch.Tensor, cameras: list[PinholeCamera], size: int | None = None) -> torch.Tensor:
    """Action maps for a batch whose rollouts may see different cameras (tasks of other scenes):
    states (B, ..., 7), cameras[b] the camera of rollout b. One batched draw per distinct camera."""
    if len(cameras) != states.shape[0]:
        raise ValueError(f"{len(cameras)} cameras for a batch of {states.shape[0]} rollouts")
    size = int(size or cameras[0].image_size)
    out = torch.empty(*states.shape[:-1], 3, size, size, device=states.device)
    groups: dict[int, list[int]] = {}
    for i, cam in enumerate(cameras):
        groups.setdefault(id(cam), []).append(i)
    for idx in groups.values():
        out[idx] = draw_action_maps(states[idx].float(), cameras[idx[0]], size=size)
    return out


def gripper_mask(states: torch.Tensor, camera: PinholeCamera, size: int | None = None, reach: float = 0.15) -> torch.Tensor:
    """states (N, 7) -> (N, S, S) bool: the pixels within `reach` image widths of the projected
    gripper (by default 3x the action map's open disc: the hand and fingers as the camera sees them):
    where a world model must keep the robot, measured apart from the rest of the frame."""
    size = int(size or camera.image_size)
    centre = _project_to(states[:, :3].to(torch.float32), camera, size)
    return (_pixel_grid(size, centre.device) - centre[:, None, None, :]).norm(dim=-1) <= reach * size
