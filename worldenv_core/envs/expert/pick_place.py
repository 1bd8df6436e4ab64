"""Pick an object and put it on / in a target (object or BDDL region).

The whole skill is one generator (:func:`pick_and_place`) built from :mod:`.motion`
primitives.  It is closed-loop where it matters: after lifting it checks (privileged
contacts) that the object is really between the fingers and re-plans the grasp with a
little random jitter if not; placing is done by *object* position, using the grip-to-object
offset measured after the lift, so off-centre (rim) grasps still land the object's body
where LIBERO's checkers look (body origin within the region / within 3 cm of a target's).
"""
from __future__ import annotations

from typing import Iterator

import logging

import numpy as np

from . import motion as M
from .context import ExpertContext
from .grasping import plan_grasp

log = logging.getLogger(__name__)

CLEARANCE = 0.04  # vertical margin over obstacles while carrying (m)


# ------------------------------------------------------------------ targets
def target_xy(ctx: ExpertContext, target: str) -> np.ndarray:
    """Where the object's body origin should end up (xy)."""
    return ctx.pos(target)[:2]


def support_z(ctx: ExpertContext, target: str, relation: str) -> float:
    """Height the object's bottom should come down to before release."""
    if ctx.is_site(target):
        lo, hi = ctx.aabb(target)
        if relation == "in":
            return float(lo[2])  # floor of the container region
        return float(ctx.pos(target)[2])
    return ctx.top_z(target)


def _corridor_top(ctx: ExpertContext, a: np.ndarray, b: np.ndarray, exclude: set[str], width: float = 0.1) -> float:
    """Highest geom point of scene objects near the straight xy segment a -> b."""
    top = -np.inf
    names = [n for n in list(ctx.sim_env.objects_dict) + list(ctx.sim_env.fixtures_dict) if n not in exclude]
    ab = b - a
    L2 = float(ab @ ab) + 1e-9
    for n in names:
        try:
            pts = ctx.geom_corners(n)
        except Exception:
            continue
        if len(pts) == 0:
            continue
        # skip big support surfaces (tables, floor): they would dominate and are below anyway
        lo, hi = pts.min(0), pts.max(0)
        if np.any(hi[:2] - lo[:2] > 0.6):
            continue
        t = np.clip(((pts[:, :2] - a) @ ab) / L2, 0.0, 1.0)
        d = np.linalg.norm(pts[:, :2] - (a + t[:, None] * ab), axis=1)
        near = pts[d < width]
        if len(near):
            top = max(top, float(near[:, 2].max()))
    return top


# ------------------------------------------------------------------ skill
def grasp(ctx: ExpertContext, obj: str, jitter: float) -> Iterator[np.ndarray]:
    """Approach from above, descend, close.  Returns True if both fingers touch ``obj``."""
    plan = plan_grasp(ctx, obj, jitter=jitter)
    log.debug("grasp %s: %s pos=%s yaw=%.2f", obj, plan.kind, np.round(plan.pos, 3), plan.yaw)
    pre = plan.pos + np.array([0.0, 0.0, plan.approach_dz])
    # rise first if we are low (e.g. after a failed attempt) so we never sweep the scene
    cur = ctx.eef_pos()
    if cur[2] < pre[2] - 0.01:
        yield from M.move_to(ctx, [cur[0], cur[1], pre[2]], gripper=M.GRIP_OPEN, tol=0.02, max_steps=30)
    # loose tolerance above the object (no full stop), precise and slower on the way down
    yield from M.move_to(ctx, pre, yaw=plan.yaw, gripper=M.GRIP_OPEN, tol=0.012, rot_tol=0.08, max_steps=60)
    yield from M.move_to(ctx, plan.pos, yaw=plan.yaw, gripper=M.GRIP_OPEN, tol=0.005,
                         max_steps=40, max_speed=0.7, settle_steps=1)
    yield from M.close_gripper(ctx)
    held = ctx.is_grasped(obj)
    log.debug("closed: held=%s opening=%.4f eef=%s obj=%s", held, ctx.gripper_opening(),
              np.round(ctx.eef_pos(), 3), np.round(ctx.pos(obj), 3))
    return held


def place(ctx: ExpertContext, obj: str, target: str, relation: str) -> Iterator[np.ndarray]:
    """Lift the grasped object, carry it over ``target`` and put it down (on) / in (in).

    Returns False (without releasing anything useful) if the object slipped out on the lift.
    """
    eef = ctx.eef_pos()
    offset = eef - ctx.pos(obj)                 # grip -> object body, fixed while held
    hang = eef[2] - ctx.bottom_z(obj)           # how far the object hangs below the grip
    goal_xy = target_xy(ctx, target) + offset[:2]
    obstacles = _corridor_top(ctx, eef[:2], goal_xy, exclude={obj})
    tgt_top = ctx.aabb(target)[1][2] if ctx.is_site(target) else ctx.top_z(target)
    carry_z = max(obstacles, tgt_top) + hang + CLEARANCE
    carry_z = max(carry_z, eef[2] + 0.04)
    yield from M.lift(ctx, carry_z, gripper=M.GRIP_CLOSE, tol=0.02, max_steps=30)
    if not ctx.is_holding(obj):
        log.debug("slipped on lift: eef=%s obj=%s", np.round(ctx.eef_pos(), 3), np.round(ctx.pos(obj), 3))
        return False
    log.debug("lifted to %.3f (carry %.3f)", ctx.eef_pos()[2], carry_z)
    yield from M.move_to(ctx, [goal_xy[0], goal_xy[1], carry_z], gripper=M.GRIP_CLOSE,
                         tol=0.01, max_steps=60)
    log.debug("over target: eef=%s goal=%s", np.round(ctx.eef_pos(), 3), np.round(goal_xy, 3))
    # correct for swing/slip: re-measure where the object is relative to the goal
    err = target_xy(ctx, target) - ctx.pos(obj)[:2]
    goal_xy = ctx.eef_pos()[:2] + err
    release_gap = 0.02 if relation == "in" else 0.01
    z_release = support_z(ctx, target, relation) + release_gap + (ctx.eef_pos()[2] - ctx.bottom_z(obj))
    z_release = min(z_release, carry_z)
    # fast most of the way down, slow for the last few centimetres
    yield from M.move_to(ctx, [goal_xy[0], goal_xy[1], z_release + 0.03], gripper=M.GRIP_CLOSE,
                         tol=0.015, rot_tol=0.2, max_steps=40)
    log.debug("near release: eef=%s z_release=%.3f", np.round(ctx.eef_pos(), 3), z_release)
    yield from M.move_to(ctx, [goal_xy[0], goal_xy[1], z_release], gripper=M.GRIP_CLOSE,
                         tol=0.006, max_steps=20, max_speed=0.6)
    log.debug("release: eef=%s obj=%s target=%s", np.round(ctx.eef_pos(), 3), np.round(ctx.pos(obj), 3),
              np.round(ctx.pos(target), 3))
    yield from M.open_gripper(ctx)
    p = ctx.eef_pos()
    yield from M.move_to(ctx, [p[0], p[1], p[2] + 0.06], gripper=M.GRIP_OPEN, tol=0.02, max_steps=15)
    return True


def pick_and_place(ctx: ExpertContext, obj_name: str, target_name: str, relation: str = "on",
                   max_attempts: int = 3) -> Iterator[np.ndarray]:
    """Full pick-and-place of ``obj_name`` onto/into ``target_name`` (object or region).

    Returns True if the placing phase ran with the object held (the caller checks success).
    """
    for attempt in range(max_attempts):
        jitter = 0.002 if attempt == 0 else 0.006
        held = yield from grasp(ctx, obj_name, jitter)
        if held and (yield from place(ctx, obj_name, target_name, relation)):
            return True
        yield from M.open_gripper(ctx)
    return False


def pick_and_place_on(ctx: ExpertContext, obj_name: str, target_name: str) -> Iterator[np.ndarray]:
    return (yield from pick_and_place(ctx, obj_name, target_name, "on"))


def pick_and_place_in(ctx: ExpertContext, obj_name: str, target_name: str) -> Iterator[np.ndarray]:
    return (yield from pick_and_place(ctx, obj_name, target_name, "in"))
