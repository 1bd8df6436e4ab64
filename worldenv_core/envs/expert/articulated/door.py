"""Hinged doors with a panel (the ``microwave`` door): swing open or shut by pushing the panel.

No grasp: the fingertips of the closed gripper press the panel near its top edge on the face
that trails the motion and follow the door's arc about the hinge.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from ..context import ExpertContext
from ..motion import (
    GRIP_CLOSE, Action, fingertip_depth, geom_extent_along, move_to, pose_action, rotation_about,
    set_gripper, target_mat_for, yaw_for_fingers_along,
)
from .joints import JointView, reached

_DEBUG = False  # print the planned contact point


def _door_panel(ctx: ExpertContext, jv: JointView) -> int:
    """The door's biggest collision geom (the panel)."""
    gs = jv.geoms()
    vol = [float(np.prod(ctx.model.geom_aabb[g][3:])) for g in gs]
    return gs[int(np.argmax(vol))]


def swing_door(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Push a hinged door panel about its hinge towards ``q_tgt``.

    The fingertips press the panel near its top edge on the face that trails the motion,
    at ~60% of the panel width from the hinge (away from a handle at the free end); the
    hand stays above the panel.  The contact point is tracked in the door's frame and the
    gripper is servoed a little ahead of it along the arc.
    """
    g = _door_panel(ctx, jv)
    ks = jv.axis * sign  # rotation axis of the desired motion
    a = jv.anchor
    Rg = ctx.data.geom_xmat[g].reshape(3, 3)
    h = ctx.model.geom_aabb[g][3:]
    c = np.array(ctx.data.geom_xpos[g]) + Rg @ ctx.model.geom_aabb[g][:3]
    horiz = [i for i in range(3) if abs(Rg[2, i]) < 0.5]
    i_long = max(horiz, key=lambda i: h[i])
    i_thin = min(range(3), key=lambda i: h[i])
    e_long = Rg[:, i_long] * (1.0 if np.dot(Rg[:, i_long], c - a) > 0 else -1.0)
    v = np.cross(ks, c - a)  # motion of the panel centre
    n = Rg[:, i_thin] * (1.0 if np.dot(Rg[:, i_thin], v) > 0 else -1.0)
    # distance of the panel centre from the hinge along the panel, and the panel's top
    d_c = float(np.dot(c - a, e_long))
    L = d_c - h[i_long] + 0.6 * 2 * h[i_long]
    top = float(c[2] + geom_extent_along(ctx, g, np.array([0, 0, 1.0])))
    tip = fingertip_depth(ctx)
    p = c + e_long * (L - d_c) - n * (h[i_thin] + 0.012)
    p[2] = top - 0.022 + tip
    # express in the door body frame so it follows the door
    R0, x0 = jv.body_mat(), jv.body_pos()
    p_local = R0.T @ (p - x0)

    def contact_now() -> np.ndarray:
        return jv.body_pos() + jv.body_mat() @ p_local

    yaw = yaw_for_fingers_along(ctx, e_long)
    q0 = jv.qpos
    if _DEBUG:
        print("door q", round(q0, 3), "contact", p.round(3), "n", n.round(2), "e_long", e_long.round(2), "top", round(top, 3))
    yield from set_gripper(ctx, GRIP_CLOSE, 2)
    yield from move_to(ctx, p + np.array([0, 0, 0.10]), yaw=yaw, gripper=GRIP_CLOSE, tol=0.015, max_steps=70)
    yield from move_to(ctx, p, yaw=yaw, gripper=GRIP_CLOSE, tol=0.008, max_steps=40, max_speed=0.6)
    R = target_mat_for(ctx, yaw)
    for k in range(max_steps):
        q = jv.qpos
        if reached(jv, q_tgt, sign):
            break
        lead = min(0.2, abs(q_tgt - q) + 0.1)
        cur = contact_now()
        tgt = a + rotation_about(ks, lead) @ (cur - a)
        tgt[2] = p[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.6)
    # back off from the panel, then up
    back = contact_now() - a
    n_now = np.cross(ks, back)
    n_now /= np.linalg.norm(n_now) + 1e-9
    yield from move_to(ctx, ctx.eef_pos() - n_now * 0.03, gripper=GRIP_CLOSE, tol=0.015, max_steps=12)
    yield from move_to(ctx, ctx.eef_pos() + np.array([0, 0, 0.08]), gripper=GRIP_CLOSE, tol=0.02, max_steps=20)
    return (jv.qpos - q0) * sign > 0
