"""Pushing for the scripted expert: a dish onto a table region (``On(plate, table_region)``).

Closed-loop planar pushing with the closed gripper; a dish (flat, wide, hollow) is driven from
inside its rim. ``on_or_push`` wraps the pick-and-place ``On`` handler so that a dish going to a
table region is pushed and everything else is picked and placed.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from .context import ExpertContext
from .motion import (
    GRIP_CLOSE, Action, fingertip_depth, geom_extent_along, move_to, pose_action, set_gripper, target_mat_for,
    yaw_for_fingers_along,
)

_DEBUG = False  # print the dish's floor and the push height


def push_to(ctx: ExpertContext, obj: str, region: str, max_steps: int = 160) -> Iterator[Action]:
    """Push ``obj`` across the table until its centre lies inside ``region`` (a table site).

    Rule for the contact: a dish (flat, wide, hollow: a plate) is pushed from *inside* its rim
    (the fingers sit in the dish and drive the leading rim, which keeps the dish captured and
    keeps the hand over the dish, clear of nearby fixtures); anything else from behind.
    """
    lo, hi = ctx.aabb(obj)
    _, half, _ = ctx.footprint(obj)
    radius = float(np.max(half))
    height = float(hi[2] - lo[2])
    dish = height < 0.035 and radius > 0.05
    tip = fingertip_depth(ctx)
    if dish:
        # floor of the dish = top of the collision geom nearest the centre
        c = ctx.pos(obj)
        gs = ctx.geom_ids(obj)
        gc = min(gs, key=lambda g: float(np.linalg.norm(ctx.data.geom_xpos[g][:2] - c[:2])))
        floor = float(ctx.data.geom_xpos[gc][2]) + geom_extent_along(ctx, gc, np.array([0, 0, 1.0]))
        push_z = floor + tip - 0.006  # press lightly on the floor so the finger cannot ride up
        dists = [float(np.linalg.norm(ctx.data.geom_xpos[g][:2] - c[:2])) for g in gs if g != gc]
        rim_r = float(np.median(dists)) if dists else radius
        if _DEBUG:
            print("dish floor", round(floor, 4), "tip", round(tip, 4), "push_z", round(push_z, 4), "lo", lo.round(3), "hi", hi.round(3))
        lead = -0.01  # finger starts just behind the centre, then drives the leading rim
    else:
        push_z = float(lo[2]) + min(0.5 * height, 0.03) + tip
        lead = radius + 0.025
        rim_r = radius

    def goal_xy() -> np.ndarray:
        return ctx.pos(region)[:2]

    def obj_xy() -> np.ndarray:
        return ctx.pos(obj)[:2]

    def dir_xy() -> np.ndarray:
        d = goal_xy() - obj_xy()
        return d / (np.linalg.norm(d) + 1e-9)

    def contact(offset: float) -> np.ndarray:
        p = np.zeros(3)
        p[:2] = obj_xy() - dir_xy() * offset
        p[2] = push_z
        return p

    size = np.abs(ctx.site_size(region)[:2])
    tol = float(min(np.min(size) * 0.4, 0.02))
    d0 = dir_xy()
    yaw = yaw_for_fingers_along(ctx, np.array([-d0[1], d0[0], 0.0]))
    yield from set_gripper(ctx, GRIP_CLOSE, 2)
    start = contact(lead)
    yield from move_to(ctx, start + np.array([0, 0, 0.10]), yaw=yaw, gripper=GRIP_CLOSE, tol=0.015, max_steps=60)
    yield from move_to(ctx, start, yaw=yaw, gripper=GRIP_CLOSE, tol=0.008, max_steps=40, max_speed=0.6)
    R = target_mat_for(ctx, yaw)
    for k in range(max_steps):
        err = goal_xy() - obj_xy()
        dist = float(np.linalg.norm(err))
        if dist < tol:
            break
        d = dir_xy()
        e = ctx.eef_pos()
        rel = e[:2] - obj_xy()
        lateral = rel - np.dot(rel, d) * d
        lost = (np.linalg.norm(rel) > rim_r or e[2] > push_z + 0.012) if dish else (
            np.linalg.norm(lateral) > 0.6 * radius or np.dot(rel, d) > 0)
        if lost:
            # lost the object: re-approach from above
            yield from move_to(ctx, e + np.array([0, 0, 0.08]), gripper=GRIP_CLOSE, tol=0.02, max_steps=20)
            b = contact(lead)
            yield from move_to(ctx, b + np.array([0, 0, 0.08]), gripper=GRIP_CLOSE, tol=0.015, max_steps=30)
            yield from move_to(ctx, b, gripper=GRIP_CLOSE, tol=0.01, max_steps=30)
            continue
        # target: advance along d from the current pusher position, steer laterally onto the line
        tgt = e.copy()
        tgt[:2] = e[:2] - lateral * 0.5 + d * min(0.02, dist + 0.005)
        tgt[2] = push_z
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.45)
    yield from move_to(ctx, ctx.eef_pos() + np.array([0, 0, 0.08]), gripper=GRIP_CLOSE, tol=0.02, max_steps=20)
    return bool(np.linalg.norm(goal_xy() - obj_xy()) < tol)


def is_dish(ctx: ExpertContext, obj: str) -> bool:
    """Flat, wide object (a plate): low enough to push, awkward to grasp."""
    try:
        lo, hi = ctx.aabb(obj)
        _, half, _ = ctx.footprint(obj)
    except Exception:  # noqa: BLE001
        return False
    return float(hi[2] - lo[2]) < 0.035 and float(np.max(half)) > 0.05


def is_table_region(ctx: ExpertContext, name: str) -> bool:
    """A region site drawn on a table (``main_table_*_region``)."""
    env = ctx.sim_env
    if name not in env.object_sites_dict:
        return False
    parent = env.object_sites_dict[name].parent_name
    if parent is None:  # LIBERO's table regions are TargetZones with no parent object
        return True
    try:
        return "table" in ctx.category(parent) or "table" in parent
    except Exception:  # noqa: BLE001
        return "table" in str(parent)


def on_or_push(pick_place_on):
    """Wrap the pick-and-place 'on' handler with the push rule: a dish onto a table region
    is pushed there (:func:`push_to`); anything else goes to ``pick_place_on``."""

    def handler(ctx: ExpertContext, obj: str, target: str) -> Iterator[Action]:
        if is_table_region(ctx, target) and is_dish(ctx, obj):
            return (yield from push_to(ctx, obj, target))
        return (yield from pick_place_on(ctx, obj, target))

    handler.__name__ = "on_or_push"
    return handler
