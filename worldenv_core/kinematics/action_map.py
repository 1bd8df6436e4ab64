"""Action maps (EVAC, World-Env sec. 4.1): the end-effector state s_{t+1} drawn into the camera
image on a black background, as pixel conditioning for the world simulator.

A filled white disc at the projected gripper position whose radius grows with the gripper
opening, and three line segments for the gripper's x (red), y (green) and z (blue) axes. Given
the arm's skeleton (`arm.SerialArm.points`), its links are drawn under them as grey capsules as
thick as the links look from the camera, the nearest link in front, shaded base (dark) to hand
(light): the whole robot, not only its gripper. Everything is drawn at once for a batch of states with distance fields over the pixel grid
(soft, anti-aliased edges), no Python loop over pixels or states.
"""

from __future__ import annotations

import torch

from worldenv_core.kinematics.arm import SEGMENT_RADIUS_M, rollout_groups
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import axis_angle_to_matrix

AXIS_LENGTH_M = 0.10
AXIS_COLOURS = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
ARM_SHADE = (0.25, 0.6)  # the base's and the hand's grey; links between are graded


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


def _draw_arm(points: torch.Tensor, camera: PinholeCamera, size: int, grid: torch.Tensor) -> torch.Tensor:
    """points (N, P, 3) the arm's skeleton -> (N, H, W) grey levels (0 where no link is seen).
    Each segment is a capsule of its link's radius at its depth; where links overlap the nearest wins."""
    if points.shape[-2] != len(SEGMENT_RADIUS_M) + 1:
        raise ValueError(f"an arm skeleton has {len(SEGMENT_RADIUS_M) + 1} points, got {points.shape[-2]}")
    uv, depth = _project_to(points, camera, size), camera.project(points)[1]
    seg_depth = (0.5 * (depth[:, :-1] + depth[:, 1:])).clamp(min=1e-3)  # (N, L)
    radius_m = torch.tensor(SEGMENT_RADIUS_M, dtype=points.dtype, device=points.device)
    radius = camera.focal * (size / camera.image_size) * radius_m / seg_depth  # (N, L) pixels
    cover = _coverage(_segment_distance(grid, uv[:, :-1], uv[:, 1:]), radius[..., None, None])  # (N, L, H, W)
    front = torch.where(cover > 0, seg_depth[..., None, None], torch.inf).argmin(dim=1, keepdim=True)
    shade = torch.linspace(*ARM_SHADE, len(SEGMENT_RADIUS_M), device=points.device)
    return cover.gather(1, front)[:, 0] * shade[front[:, 0]]


def draw_action_maps(states: torch.Tensor, camera: PinholeCamera, size: int | None = None,
                     radius_px: tuple[float, float] | None = None, line_px: float | None = None,
                     arm_points: torch.Tensor | None = None) -> torch.Tensor:
    """states (..., 7) = (eef pos, eef axis-angle, gripper opening in [0, 1]) ->
    maps (..., 3, S, S) in [0, 1], S = `size` (default: the camera's resolution; a world model
    that only patch-embeds its maps can take them smaller, and drawing costs S^2). Radii default
    to a fraction of the size so that maps look alike at every resolution: a disc of 2 %..5 % of
    the width, lines of 0.8 %. `arm_points` (..., P, 3): the arm's skeleton for each state, drawn
    under the gripper (None: the gripper alone)."""
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
    if arm_points is not None:
        if arm_points.shape[:-2] != lead:
            raise ValueError(f"arm_points {tuple(arm_points.shape)} do not match states {tuple(states.shape)}")
        arm = _draw_arm(arm_points.reshape(-1, *arm_points.shape[-2:]).to(torch.float32), camera, size, grid)
        img = img + (1 - disc[:, None]) * arm[:, None]  # the links under the disc
    for axis in range(3):  # paint the three axes over the disc (3 iterations, whole batch each)
        alpha = lines[:, axis, None]
        img = img * (1 - alpha) + alpha * colours[axis][None, :, None, None]
    return img.reshape(*lead, 3, size, size)


def draw_action_maps_per_rollout(states: torch.Tensor, cameras: list[PinholeCamera], size: int | None = None,
                                 arm_points: torch.Tensor | None = None) -> torch.Tensor:
    """Action maps for a batch whose rollouts may see different cameras (tasks of other scenes):
    states (B, ..., 7), cameras[b] the camera of rollout b, arm_points (B, ..., P, 3) or None.
    One batched draw per distinct camera."""
    if len(cameras) != states.shape[0]:
        raise ValueError(f"{len(cameras)} cameras for a batch of {states.shape[0]} rollouts")
    size = int(size or cameras[0].image_size)
    out = torch.empty(*states.shape[:-1], 3, size, size, device=states.device)
    for _, idx in rollout_groups(cameras):
        out[idx] = draw_action_maps(states[idx].float(), cameras[idx[0]], size=size,
                                    arm_points=None if arm_points is None else arm_points[idx])
    return out


def gripper_mask(states: torch.Tensor, camera: PinholeCamera, size: int | None = None, reach: float = 0.15) -> torch.Tensor:
    """states (N, 7) -> (N, S, S) bool: the pixels within `reach` image widths of the projected
    gripper (by default 3x the action map's open disc: the hand and fingers as the camera sees them):
    where a world model must keep the robot, measured apart from the rest of the frame."""
    size = int(size or camera.image_size)
    centre = _project_to(states[:, :3].to(torch.float32), camera, size)
    return (_pixel_grid(size, centre.device) - centre[:, None, None, :]).norm(dim=-1) <= reach * size


def arm_mask(points: torch.Tensor, camera: PinholeCamera, size: int | None = None, grow_px: int = 1) -> torch.Tensor:
    """points (N, P, 3) the arm's skeletons (`SerialArm.points` of the real joints) -> (N, S, S) bool: the
    pixels its drawn links cover, grown by `grow_px` (the links are capsules, the real ones are not): the
    whole robot's region, where open-loop fidelity scores the arm apart from the scene."""
    size = int(size or camera.image_size)
    grey = _draw_arm(points.to(torch.float32), camera, size, _pixel_grid(size, points.device))
    mask = (grey > 0.05).float()[:, None]
    if grow_px > 0:
        mask = torch.nn.functional.max_pool2d(mask, 2 * grow_px + 1, stride=1, padding=grow_px)
    return mask[:, 0] > 0
