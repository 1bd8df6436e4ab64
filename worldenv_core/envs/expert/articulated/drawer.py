"""Drawers (slide joints: the ``wooden_cabinet`` / ``white_cabinet`` drawers): pull open, push shut.

The handle is the drawer's collision geom that sticks out furthest along the opening
direction.  *Open*: side grasp of the handle (gripper horizontal, pointing into the cabinet,
fingers closing vertically on the bar), pull along the slide axis, back off, turn back to
top-down.  A top-down grasp cannot work: the Panda hand is ~20 cm wide along its closing axis
and hits the cabinet front/top.  *Close*: fingertips of the closed gripper, pitched 45 degrees
down along the slide axis, push the handle in (keeps the forearm off the cabinet top and the
wrist off whatever stands behind).

Both are generators of 7-D OSC_POSE actions returning whether the joint moved the right way.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from ..context import ExpertContext
from ..motion import (
    GRIP_CLOSE, GRIP_OPEN, Action, fingertip_depth, geom_extent_along, grip, move_to, pose_action,
    rotate_smoothly, servo, set_gripper,
)
from .joints import JointView, fixture_top, reached

_DEBUG = False  # print the planned handle grasp


def _handle_geom(ctx: ExpertContext, jv: JointView, out_dir: np.ndarray) -> int:
    gs = jv.geoms()
    proj = [float(np.dot(ctx.data.geom_xpos[g], out_dir)) for g in gs]
    return gs[int(np.argmax(proj))]


def _side_grasp_mat(ctx: ExpertContext, approach: np.ndarray) -> np.ndarray:
    """Gripper pointing horizontally along ``approach`` with the fingers closing vertically.

    The grip-site frame has z = approach (towards the fingertips) and x = closing axis; of
    the two mirror solutions take the one nearer the current orientation.
    """
    z = approach / (np.linalg.norm(approach) + 1e-9)
    return _nearest_frame(ctx, z, [np.array([0.0, 0.0, sx]) for sx in (1.0, -1.0)])


def _horizontal_push_mat(ctx: ExpertContext, push: np.ndarray, pitch: float = np.pi / 4) -> np.ndarray:
    """Gripper pointing along ``push`` tilted down by ``pitch`` (fingertips lead, the wrist
    and forearm stay up and back), fingers closing horizontally across ``push``."""
    z = push * np.cos(pitch) - np.array([0.0, 0.0, 1.0]) * np.sin(pitch)
    z /= np.linalg.norm(z) + 1e-9
    xs = [np.cross(np.array([0.0, 0.0, 1.0]), push) * sx for sx in (1.0, -1.0)]
    return _nearest_frame(ctx, z, [x / (np.linalg.norm(x) + 1e-9) for x in xs])


def _nearest_frame(ctx: ExpertContext, z: np.ndarray, xs: list[np.ndarray]) -> np.ndarray:
    """Of the grip-site frames with approach axis `z` and closing axis one of `xs` (mirror
    solutions), the one nearest the current orientation."""
    cur = ctx.eef_mat()
    best, best_ang = None, np.inf
    for x in xs:
        y = np.cross(z, x)
        R = np.stack([x, y, z], axis=1)
        ang = np.arccos(np.clip((np.trace(R @ cur.T) - 1) / 2, -1, 1))
        if ang < best_ang:
            best, best_ang = R, ang
    return best


def pull_drawer(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Side grasp of the drawer handle (gripper horizontal, fingers above/below the bar), pull.

    A top-down grasp does not fit: the Panda hand is ~20 cm wide along the closing axis and
    would hit the cabinet front/top; approaching along the slide axis keeps it in free space.
    """
    out = jv.axis * sign  # direction the handle moves when opening
    out[2] = 0.0
    out /= np.linalg.norm(out) + 1e-9
    g = _handle_geom(ctx, jv, out)
    h = np.array(ctx.data.geom_xpos[g])
    half = geom_extent_along(ctx, g, out)
    R_start, pos_start = ctx.eef_mat(), ctx.eef_pos()
    R = _side_grasp_mat(ctx, -out)
    grasp = h + out * (half * 0.2)
    pre = grasp + out * 0.10
    high = pre.copy()
    high[2] = max(pre[2], ctx.eef_pos()[2])
    if _DEBUG:
        print("handle", h.round(4), "grasp", grasp.round(4), "R", R.round(2).tolist())
    yield from grip(ctx, GRIP_OPEN, ctx.eef_mat(), min_steps=1)
    yield from rotate_smoothly(ctx, high, R, GRIP_OPEN, max_rate=0.3, max_steps=40, done_ang=0.3)
    yield from servo(ctx, pre, R, GRIP_OPEN, tol=0.008, max_steps=50)
    yield from servo(ctx, grasp, R, GRIP_OPEN, tol=0.005, max_steps=40, max_speed=0.6, settle=1)
    yield from grip(ctx, GRIP_CLOSE, R)
    # pull along the slide axis until the joint passes the target
    start_q = jv.qpos
    for k in range(max_steps):
        q = jv.qpos
        if reached(jv, q_tgt, sign):
            break
        remaining = abs(q_tgt - q) + 0.01
        tgt = ctx.eef_pos() + out * min(0.03, remaining)
        tgt[2] = grasp[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.6)
    # a few steps free the bar (the fingers straddle it vertically and back off along the
    # slide); waiting for the fingers to come to rest would only cost time
    yield from grip(ctx, GRIP_OPEN, R, min_steps=3, max_steps=6)
    # back off along the slide axis and rise clear of the fixture before turning the wrist
    # back to top-down (the turning hand sweeps ~10 cm around the grip site)
    p = ctx.eef_pos() + out * 0.07
    p[2] = max(p[2] + 0.04, fixture_top(ctx, name) + 0.03)
    yield from servo(ctx, p, R, GRIP_OPEN, tol=0.025, max_steps=25)
    yield from _back_to_start(ctx, p, pos_start, R_start, GRIP_OPEN)
    return (jv.qpos - start_q) * sign > 0


def push_drawer(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Push the drawer shut with the fingertips of the (closed) horizontal gripper on the
    handle.  A top-down hand would bring the forearm onto the cabinet top when the drawer
    is low and deep; pointing the gripper along the slide keeps the arm back."""
    push = jv.axis * sign  # direction the drawer moves when closing
    push[2] = 0.0
    push /= np.linalg.norm(push) + 1e-9
    g = _handle_geom(ctx, jv, -push)
    h = np.array(ctx.data.geom_xpos[g])
    half = geom_extent_along(ctx, g, push)
    tip = fingertip_depth(ctx)
    R_start, pos_start = ctx.eef_mat(), ctx.eef_pos()
    R = _horizontal_push_mat(ctx, push)
    a = R[:, 2]  # approach axis (towards the fingertips)
    start = h - push * (half + 0.012) - a * tip
    pre = start - push * 0.06 + np.array([0, 0, 0.04])
    high = pre.copy()
    high[2] = max(pre[2] + 0.05, ctx.eef_pos()[2])
    yield from set_gripper(ctx, GRIP_CLOSE, 2)
    yield from rotate_smoothly(ctx, high, R, GRIP_CLOSE, max_rate=0.3, max_steps=40, done_ang=0.3)
    yield from servo(ctx, pre, R, GRIP_CLOSE, tol=0.01, max_steps=40)
    yield from servo(ctx, start, R, GRIP_CLOSE, tol=0.008, max_steps=30, max_speed=0.6)
    start_q = jv.qpos
    for k in range(max_steps):
        q = jv.qpos
        if reached(jv, q_tgt, sign):
            break
        tgt = ctx.eef_pos() + push * 0.03
        tgt[2] = start[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.7)
    p = ctx.eef_pos() - push * 0.06
    p[2] += 0.04
    yield from servo(ctx, p, R, GRIP_CLOSE, tol=0.02, max_steps=20)
    yield from _back_to_start(ctx, p, pos_start, R_start, GRIP_CLOSE)
    return (jv.qpos - start_q) * sign > 0


def _back_to_start(ctx: ExpertContext, p: np.ndarray, pos_start: np.ndarray, R_start: np.ndarray,
                   gripper: float) -> Iterator[Action]:
    """From `p` clear of the drawer: turn back towards the starting orientation while heading back
    to the start position (the nominal arm configuration for whatever comes next), then finish
    exactly top-down with the gripper open (a residual tilt spoils the next top-down grasp)."""
    mid = 0.5 * (p + pos_start)
    mid[2] = max(p[2], pos_start[2])
    yield from rotate_smoothly(ctx, mid, R_start, gripper)
    yield from move_to(ctx, ctx.eef_pos(), yaw=None, gripper=GRIP_OPEN, tol=0.03, rot_tol=0.04, max_steps=15)
