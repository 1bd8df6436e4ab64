"""Knobs (the ``flat_stove`` button: a hinge about z with turn-on/turn-off ranges): turn it.

Top-down grasp of the knob's top fin with the fingers across it, then turn the wrist by the
angle the joint has to go (the knob turns about world z, like the wrist's yaw).
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from ..context import ExpertContext, top_down_mat
from ..motion import (
    GRIP_CLOSE, GRIP_OPEN, Action, close_gripper, geom_extent_along, grip, move_to, pose_action,
    yaw_for_fingers_along,
)
from .joints import JointView, reached


def turn_knob(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Grasp the knob's fin from above and twist it towards ``q_tgt``."""
    gs = jv.geoms()
    tops = [float(ctx.data.geom_xpos[g][2] + geom_extent_along(ctx, g, np.array([0, 0, 1.0]))) for g in gs]
    g = gs[int(np.argmax(tops))]  # the grip fin on top of the knob
    ztop = max(tops)
    R = ctx.data.geom_xmat[g].reshape(3, 3)
    h = ctx.model.geom_aabb[g][3:]
    # thinnest horizontal direction of the fin = finger closing direction
    cands = []
    for i in range(3):
        d = R[:, i].copy()
        d[2] = 0
        if np.linalg.norm(d) < 0.7:
            continue
        cands.append((h[i], d / np.linalg.norm(d)))
    across = min(cands, key=lambda t: t[0])[1]
    yaw0 = yaw_for_fingers_along(ctx, across)
    grasp = jv.anchor.copy()
    grasp[2] = ztop - 0.015
    yield from move_to(ctx, grasp + np.array([0, 0, 0.12]), yaw=yaw0, gripper=GRIP_OPEN, tol=0.02, max_steps=60)
    yield from move_to(ctx, grasp + np.array([0, 0, 0.03]), yaw=yaw0, gripper=GRIP_OPEN, tol=0.01, max_steps=40)
    yield from move_to(ctx, grasp, yaw=yaw0, gripper=GRIP_OPEN, tol=0.006, max_steps=40, max_speed=0.5, settle_steps=2)
    yield from close_gripper(ctx)
    q0 = jv.qpos
    # knob turns about world z (axis * sign): turn the wrist by the same angle
    turn_sign = float(np.sign(np.dot(jv.axis, [0, 0, 1.0]))) * sign
    yaw_start = ctx.eef_yaw()
    yaw_goal = yaw_start + turn_sign * (abs(q_tgt - q0) + 0.25)

    for k in range(max_steps):
        q = jv.qpos
        if reached(jv, q_tgt, sign):
            break
        # rotate at most ~0.2 rad per step towards the goal yaw
        cur = ctx.eef_yaw()
        dy = float(np.clip((yaw_goal - cur + np.pi) % (2 * np.pi) - np.pi, -0.2, 0.2))
        yield pose_action(ctx, grasp, gripper=GRIP_CLOSE, target_mat=top_down_mat(cur + dy), rot_gain=1.0)
    yield from grip(ctx, GRIP_OPEN, ctx.eef_mat(), min_steps=3)
    up = grasp + np.array([0, 0, 0.08])
    yield from move_to(ctx, up, yaw=yaw_start, gripper=GRIP_OPEN, tol=0.02, rot_tol=0.15, max_steps=30)
    return (jv.qpos - q0) * sign > 0
