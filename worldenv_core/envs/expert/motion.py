"""Low-level servo primitives for the scripted expert.

Every primitive is a **generator that yields 7-D ``np.float64`` actions** for robosuite's
OSC_POSE controller (``[dx, dy, dz, drx, dry, drz, gripper]``, each in [-1, 1]; position
units are 0.05 m and rotation units 0.5 rad per control step; gripper -1 open, +1 close).
The caller steps the env with each yielded action and then resumes the generator, which reads
the new state through the :class:`~.context.ExpertContext`.  Primitives compose with
``yield from``; a primitive simply returns when it reached its goal or timed out (its
return value is ``True`` on success, ``False`` on timeout) so the caller can decide.

Public, stable names (other modules import them; do not rename):
``GRIP_OPEN, GRIP_CLOSE, make_action, pose_action, move_to, move_through, hold,
open_gripper, close_gripper, lift, move_relative, rotate_to``; and for orientations other
than top-down (the articulated and push skills): ``servo, rotate_smoothly, grip,
set_gripper, rotation_about, yaw_for_fingers_along, geom_extent_along, fingertip_depth``.
"""
from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np
import robosuite.utils.transform_utils as T

from .context import ExpertContext, top_down_mat, wrap_half_pi

GRIP_OPEN = -1.0
GRIP_CLOSE = 1.0

# OSC scaling of one unit action (see robosuite controller config for LIBERO).
POS_SCALE = 0.05
ROT_SCALE = 0.5

Action = np.ndarray
Motion = Iterator[np.ndarray]


def make_action(dpos=(0.0, 0.0, 0.0), drot=(0.0, 0.0, 0.0), gripper: float = GRIP_OPEN) -> Action:
    """Assemble and clip a 7-D action."""
    a = np.zeros(7, dtype=np.float64)
    a[:3] = dpos
    a[3:6] = drot
    a[6] = gripper
    return np.clip(a, -1.0, 1.0)


def _rot_error(ctx: ExpertContext, target_mat: np.ndarray) -> np.ndarray:
    """World-frame axis-angle taking the current eef orientation to ``target_mat``.

    OSC applies the rotation delta on the left (goal = R(delta) @ current), so the error is
    the axis-angle of ``target @ current^T``.
    """
    R = target_mat @ ctx.eef_mat().T
    return T.quat2axisangle(T.mat2quat(R))


def target_mat_for(ctx: ExpertContext, yaw: float | None) -> np.ndarray:
    """Top-down orientation for ``yaw``; ``None`` keeps the current yaw (still top-down).

    A yaw target is wrapped to the nearest equivalent (the gripper is symmetric under a
    half turn) so the wrist never spins more than 90 degrees.
    """
    cur = ctx.eef_yaw()
    if yaw is None:
        return top_down_mat(cur)
    return top_down_mat(cur + wrap_half_pi(yaw - cur))


def pose_action(
    ctx: ExpertContext,
    pos: np.ndarray,
    yaw: float | None = None,
    gripper: float = GRIP_OPEN,
    pos_gain: float = 1.5,
    rot_gain: float = 1.5,
    max_speed: float = 1.0,
    target_mat: np.ndarray | None = None,
) -> Action:
    """One proportional-control step towards (pos, yaw).

    ``pos_gain`` is in units of "fraction of the error per step": 1.0 commands the whole
    remaining error as this step's delta (OSC's own gains then undershoot a bit, which keeps
    it smooth); the translation is capped at ``max_speed`` per axis (units of the 0.05 m
    action scale; measured: a saturated axis actually moves ~1.2 cm per control step).
    """
    err = np.asarray(pos, dtype=float) - ctx.eef_pos()
    dpos = pos_gain * err / POS_SCALE
    # Cap by the largest component (not the Euclidean norm): OSC tracks each axis
    # independently and a saturated axis moves only ~1.2 cm/step, so diagonal moves get
    # their full per-axis speed while the direction is preserved.
    n = np.max(np.abs(dpos))
    if n > max_speed:
        dpos *= max_speed / n
    R = target_mat if target_mat is not None else target_mat_for(ctx, yaw)
    drot = np.clip(rot_gain * _rot_error(ctx, R) / ROT_SCALE, -1.0, 1.0)
    return make_action(dpos, drot, gripper)


def move_to(
    ctx: ExpertContext,
    pos: Sequence[float],
    yaw: float | None = None,
    gripper: float = GRIP_OPEN,
    tol: float = 0.006,
    rot_tol: float = 0.05,
    max_steps: int = 80,
    max_speed: float = 1.0,
    pos_gain: float = 1.5,
    settle_steps: int = 0,
) -> Iterator[Action]:
    """Servo the grip site to ``pos`` (and top-down ``yaw``) until within tolerance.

    Returns True if converged, False on timeout.  ``settle_steps`` extra steps are spent
    at the goal once converged (lets the arm's velocity die down before a grasp).
    """
    pos = np.asarray(pos, dtype=float)
    R = target_mat_for(ctx, yaw)  # fixed once so the wrap decision does not flip mid-way
    for _ in range(max_steps):
        perr = np.linalg.norm(pos - ctx.eef_pos())
        rerr = np.linalg.norm(_rot_error(ctx, R))
        if perr < tol and rerr < rot_tol:
            for _ in range(settle_steps):
                yield pose_action(ctx, pos, gripper=gripper, target_mat=R, pos_gain=pos_gain)
            return True
        yield pose_action(ctx, pos, gripper=gripper, max_speed=max_speed, target_mat=R, pos_gain=pos_gain)
    return False


def move_through(
    ctx: ExpertContext,
    waypoints: Sequence[Sequence[float]],
    yaw: float | None = None,
    gripper: float = GRIP_OPEN,
    tol: float = 0.015,
    final_tol: float = 0.006,
    max_steps_each: int = 80,
    max_speed: float = 1.0,
) -> Iterator[Action]:
    """Visit waypoints in order; intermediate ones with a loose tolerance (no stopping)."""
    ok = True
    for i, wp in enumerate(waypoints):
        last = i == len(waypoints) - 1
        ok = yield from move_to(
            ctx, wp, yaw=yaw, gripper=gripper, tol=final_tol if last else tol,
            rot_tol=0.05 if last else 0.2, max_steps=max_steps_each, max_speed=max_speed,
        )
    return ok


def rotate_to(ctx: ExpertContext, yaw: float, gripper: float = GRIP_OPEN, max_steps: int = 30) -> Iterator[Action]:
    """Turn the wrist to ``yaw`` while holding the current position."""
    return (yield from move_to(ctx, ctx.eef_pos(), yaw=yaw, gripper=gripper, max_steps=max_steps))


def hold(ctx: ExpertContext, steps: int, gripper: float = GRIP_OPEN, pos: np.ndarray | None = None) -> Iterator[Action]:
    """Keep the pose (position and orientation) for ``steps`` steps with a gripper command."""
    pos = ctx.eef_pos() if pos is None else np.asarray(pos, dtype=float)
    R = target_mat_for(ctx, None)
    for _ in range(steps):
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R)
    return True


def _actuate_gripper(ctx: ExpertContext, command: float, min_steps: int, max_steps: int) -> Iterator[Action]:
    """Command the gripper while holding pose; stop once the fingers stop moving."""
    pos = ctx.eef_pos()
    R = target_mat_for(ctx, None)
    prev = ctx.gripper_opening()
    for k in range(max_steps):
        yield pose_action(ctx, pos, gripper=command, target_mat=R)
        cur = ctx.gripper_opening()
        if k + 1 >= min_steps and abs(cur - prev) < 2e-4:
            return True
        prev = cur
    return True


def close_gripper(ctx: ExpertContext, min_steps: int = 6, max_steps: int = 15) -> Iterator[Action]:
    """Close and wait until the fingers settle (on the object or fully shut)."""
    return (yield from _actuate_gripper(ctx, GRIP_CLOSE, min_steps, max_steps))


def open_gripper(ctx: ExpertContext, min_steps: int = 5, max_steps: int = 12) -> Iterator[Action]:
    """Open and wait until the fingers settle."""
    return (yield from _actuate_gripper(ctx, GRIP_OPEN, min_steps, max_steps))


def move_relative(
    ctx: ExpertContext, delta: Sequence[float], gripper: float = GRIP_OPEN, **kw
) -> Iterator[Action]:
    """Move by ``delta`` (world frame) from the current grip-site position."""
    return (yield from move_to(ctx, ctx.eef_pos() + np.asarray(delta, dtype=float), gripper=gripper, **kw))


def lift(ctx: ExpertContext, z: float, gripper: float = GRIP_CLOSE, **kw) -> Iterator[Action]:
    """Rise vertically to absolute height ``z`` (keeps x, y) holding the gripper command."""
    p = ctx.eef_pos()
    p[2] = max(z, p[2])
    kw.setdefault("tol", 0.01)
    return (yield from move_to(ctx, p, gripper=gripper, **kw))


# ---------------------------------------------------------------------------- any orientation
# The primitives above hold the gripper top-down; these servo to an arbitrary orientation
# matrix (side grasps, pitched pushes) and supply the geometry the contact skills plan with.
def rotation_about(axis: np.ndarray, ang: float) -> np.ndarray:
    """Rotation matrix about a unit ``axis`` by ``ang`` (Rodrigues)."""
    k = axis / (np.linalg.norm(axis) + 1e-12)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * (K @ K)


def yaw_for_fingers_along(ctx: ExpertContext, direction: np.ndarray) -> float:
    """Top-down yaw such that the fingers close along the horizontal ``direction``."""
    f = ctx.finger_axis()
    cur = ctx.eef_yaw()
    a_f = np.arctan2(f[1], f[0])
    a_d = np.arctan2(direction[1], direction[0])
    return float(cur + (a_d - a_f))


def geom_extent_along(ctx: ExpertContext, g: int, d: np.ndarray) -> float:
    """Half-extent of geom ``g``'s local AABB projected on world direction ``d``."""
    R = ctx.data.geom_xmat[g].reshape(3, 3)
    h = ctx.model.geom_aabb[g][3:]
    return float(np.sum(np.abs(R.T @ d) * h))


def fingertip_depth(ctx: ExpertContext) -> float:
    """How far the lowest finger point sits below the grip site (top-down gripper)."""
    g = ctx.robot.gripper
    lows = []
    for key in ("left_finger", "right_finger"):
        for n in g.important_geoms[key]:
            gid = ctx.model.geom_name2id(n)
            lows.append(ctx.data.geom_xpos[gid][2] - geom_extent_along(ctx, gid, np.array([0, 0, 1.0])))
    return float(ctx.eef_pos()[2] - min(lows))


def set_gripper(ctx: ExpertContext, command: float, steps: int, R: np.ndarray | None = None) -> Iterator[Action]:
    """Drive the gripper for exactly ``steps`` steps (4 steps ~ a full swing) holding pose.

    ``R`` is the orientation to hold (default: the current top-down yaw)."""
    pos = ctx.eef_pos()
    R = target_mat_for(ctx, None) if R is None else R
    for _ in range(steps):
        yield pose_action(ctx, pos, gripper=command, target_mat=R)


def grip(ctx: ExpertContext, command: float, R: np.ndarray, min_steps: int = 6, max_steps: int = 15) -> Iterator[Action]:
    """Open/close holding position and an arbitrary orientation; stop when the fingers settle."""
    pos = ctx.eef_pos()
    prev = ctx.gripper_opening()
    for k in range(max_steps):
        yield pose_action(ctx, pos, gripper=command, target_mat=R)
        cur = ctx.gripper_opening()
        if k + 1 >= min_steps and abs(cur - prev) < 2e-4:
            break
        prev = cur


def servo(ctx: ExpertContext, pos: np.ndarray, R: np.ndarray, gripper: float, tol: float, max_steps: int,
          max_speed: float = 1.0, rot_tol: float = 0.06, settle: int = 0) -> Iterator[Action]:
    """move_to with an arbitrary target orientation matrix."""
    for _ in range(max_steps):
        if np.linalg.norm(pos - ctx.eef_pos()) < tol and np.linalg.norm(_rot_error(ctx, R)) < rot_tol:
            break
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R, max_speed=max_speed)
    for _ in range(settle):
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R, max_speed=max_speed)


def rotate_smoothly(ctx: ExpertContext, pos: np.ndarray, R_goal: np.ndarray, gripper: float,
                    max_rate: float = 0.25, max_steps: int = 25, done_ang: float = 0.2) -> Iterator[Action]:
    """Servo to ``pos`` while turning to ``R_goal`` along the geodesic, at most ``max_rate``
    rad of new target per step (one large rotation command makes the OSC flail)."""
    for _ in range(max_steps):
        err = _rot_error(ctx, R_goal)
        ang = float(np.linalg.norm(err))
        if ang < done_ang and np.linalg.norm(pos - ctx.eef_pos()) < 0.03:
            break
        R_t = R_goal if ang < 1e-6 else rotation_about(err / ang, min(ang, max_rate)) @ ctx.eef_mat()
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R_t)
