"""Pick an object and put it on / in a target (object or BDDL region).

The whole skill is one generator (:func:`pick_and_place`) built from :mod:`.motion`
primitives.  It is closed-loop where it matters: after lifting it checks (privileged
contacts) that the object is really between the fingers and re-plans the grasp with a
little random jitter if not; placing is done by *object* position, using the grip-to-object
offset measured after the lift, so off-centre (rim) grasps still land the object's body
where LIBERO's checkers look (body origin within the region / within 3 cm of a target's).

:func:`clear_of_boxes` makes room before a drawer is opened: an object standing where the
open drawer will overhang it is slid a few centimetres aside first (the planner calls it
through ``articulated.ensure_accessible``).
"""
from __future__ import annotations

from typing import Iterator

import logging

import numpy as np

from . import motion as M
from .context import ExpertContext
from .grasping import HAND_HALF, _obstacle_points, _robot_base_xy, plan_grasp

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


# ------------------------------------------------------------------ making room
Box = tuple[np.ndarray, np.ndarray]


def _boxes_dist(xy: np.ndarray, boxes: list[Box]) -> float:
    """xy distance from a point to the nearest of some axis-aligned boxes (0 inside)."""
    return min(float(np.linalg.norm(np.maximum(np.maximum(lo[:2] - xy, xy - hi[:2]), 0.0)))
               for lo, hi in boxes)


def free_spot(ctx: ExpertContext, obj: str, boxes: list[Box],
              margin: float = 0.015, max_shift: float = 0.12) -> np.ndarray | None:
    """Nearest table spot (xy of the footprint centre) from which ``obj`` can be grasped
    with the palm clear of the boxes, its footprint clear of every other object by
    ``margin``; among equally short shifts the most open one, leaning towards the robot
    (the far side of the table is at the edge of reach)."""
    centre, half, _ = ctx.footprint(obj)
    radius = float(np.max(half))
    others = _obstacle_points(ctx, obj, z_above=ctx.bottom_z(obj) + 0.005)
    # The grasp it would get now, carried along with it: its palm footprint (sampled on a
    # grid; the boxes are axis-aligned) must stay out from under the boxes.  A rim grasp may
    # take any side of a round vessel, so for those every turn about the centre counts.
    plan = plan_grasp(ctx, obj)
    u = np.linspace(-1, 1, 5)
    turns = np.linspace(0, 2 * np.pi, 12, endpoint=False) if plan.kind == "rim" else [0.0, np.pi]
    palms = []
    for phi in turns:
        yaw = plan.yaw + phi
        ax, perp = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        Rz = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
        grip = Rz @ (plan.pos[:2] - centre)
        palms.append(np.array([grip + a * HAND_HALF[0] * ax + b * HAND_HALF[1] * perp for a in u for b in u]))
    to_robot = _robot_base_xy(ctx) - centre
    to_robot /= np.linalg.norm(to_robot) + 1e-9
    # first keep the grasp side planned now (usually the robot-facing one: quick to reach);
    # only if that finds no spot, any side
    for usable in (palms[:1], palms):
        for dist in np.arange(0.02, max_shift + 1e-9, 0.01):
            best, best_score = None, -np.inf
            for ang in np.linspace(-np.pi, np.pi, 24, endpoint=False):
                d = np.array([np.cos(ang), np.sin(ang)])
                c = centre + dist * d
                if not any(min(_boxes_dist(c + q, boxes) for q in palm) >= margin for palm in usable):
                    continue
                clear = float(np.min(np.linalg.norm(others - c, axis=1))) - radius if len(others) else 1.0
                if clear < margin:
                    continue
                score = min(clear, 0.05) + 0.02 * float(d @ to_robot)
                if score > best_score:
                    best, best_score = c, score
            if best is not None:
                return best
    return None


def clear_of_boxes(ctx: ExpertContext, obj: str, boxes: list[Box],
                   margin: float = 0.015) -> Iterator[np.ndarray]:
    """If ``obj`` stands (partly) under the boxes -- e.g. where a drawer about to be opened
    will overhang it -- slide it out: grasp, lift ~2 cm, move to :func:`free_spot`, set down.

    Cheaper than a full pick-and-place (no carry height) and the only way to keep the
    object graspable from above afterwards.  Returns True if nothing had to move or the move
    was done.
    """
    centre, half, _ = ctx.footprint(obj)
    radius = float(np.max(half))
    top = ctx.top_z(obj)
    over = [b for b in boxes if b[0][2] > top]  # overhanging parts; taller ones just collide
    if not over or _boxes_dist(centre, over) >= radius + margin:
        return True
    spot = free_spot(ctx, obj, over, margin)
    if spot is None:
        return False
    log.debug("clearing %s from under the box: %s -> %s", obj, np.round(centre, 3), np.round(spot, 3))
    for attempt in range(2):
        held = yield from grasp(ctx, obj, 0.002 if attempt == 0 else 0.006)
        if held:
            break
        yield from M.open_gripper(ctx)
    else:
        return False
    eef = ctx.eef_pos()
    goal = eef.copy()
    goal[:2] += spot - centre
    yield from M.lift(ctx, eef[2] + 0.02, gripper=M.GRIP_CLOSE, tol=0.008, max_steps=10)
    yield from M.move_to(ctx, [goal[0], goal[1], eef[2] + 0.02], gripper=M.GRIP_CLOSE, tol=0.008,
                         max_steps=25, max_speed=0.8)
    yield from M.move_to(ctx, [goal[0], goal[1], eef[2] + 0.004], gripper=M.GRIP_CLOSE, tol=0.006,
                         max_steps=8, max_speed=0.5)
    # a half-open hand already lets go of it; rising does not need the fingers at rest
    yield from M.open_gripper(ctx, min_steps=3, max_steps=6)
    p = ctx.eef_pos()
    yield from M.move_to(ctx, [p[0], p[1], p[2] + 0.05], gripper=M.GRIP_OPEN, tol=0.02, max_steps=10)
    return True
