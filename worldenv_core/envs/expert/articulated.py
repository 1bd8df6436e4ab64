"""Articulated-object primitives for the scripted expert: drawers, doors, knobs.

All primitives are generators yielding 7-D OSC_POSE actions (see :mod:`.motion`).  They read
the articulation straight from MuJoCo (joint type, axis, anchor, current qpos, the collision
geoms of the moving body) and the open/close/turn-on thresholds from the LIBERO object class
(``object_properties["articulation"]``), so one rule serves every instance:

* **slide joints** (``wooden_cabinet`` / ``white_cabinet`` drawers): the handle is the
  moving body's collision geom that sticks out furthest along the opening direction.
  *Open*: side grasp of the handle (gripper horizontal, pointing into the cabinet, fingers
  closing vertically on the bar), pull along the slide axis, back off, turn back to
  top-down.  A top-down grasp cannot work: the Panda hand is ~20 cm wide along its closing
  axis and hits the cabinet front/top.  *Close*: fingertips of the closed gripper, pitched
  45 degrees down along the slide axis, push the handle in (keeps the forearm off the
  cabinet top and the wrist off whatever stands behind).
* **hinge joints with a panel** (``microwave`` door): the fingertips press the panel near its
  top edge on the face that trails the motion, following the door's arc.
* **knobs** (``flat_stove`` button: hinge about z, found by having turn-on ranges): top-down
  grasp of the knob's top fin with the fingers across it, then turn the wrist.
Pushing a dish onto a table region lives in :mod:`.push`.

Success thresholds come from the LIBERO object (e.g. drawer open iff q < -0.14, stove on iff
q >= 0.5); each primitive drives its joint a margin past the threshold and stops when it is
there or when it is past the threshold and has stopped moving (a shut drawer).

Public API::

    open_region(ctx, region)   close_region(ctx, region)      # region or object name
    turn_on(ctx, obj)          turn_off(ctx, obj)
    articulated_container(ctx, region, relation) -> what to open before 'in' (or None)
    ensure_accessible(ctx, region, relation, obj) # planner precondition (+ make room for obj)
    opened_boxes(ctx, drawer) -> where the drawer's geoms will be once open
    is_open(ctx, name) / is_closed(ctx, name)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .context import ExpertContext
from .motion import GRIP_CLOSE, GRIP_OPEN, close_gripper, move_to, pose_action, target_mat_for

Action = np.ndarray

SLIDE, HINGE = 2, 3  # mujoco joint types
_DEBUG = False


# ---------------------------------------------------------------------------- joint access
@dataclass
class JointView:
    """Live view of one articulation joint."""

    ctx: ExpertContext
    name: str

    @property
    def jid(self) -> int:
        return self.ctx.model.joint_name2id(self.name)

    @property
    def type(self) -> int:
        return int(self.ctx.model.jnt_type[self.jid])

    @property
    def qpos(self) -> float:
        return float(self.ctx.data.qpos[self.ctx.model.jnt_qposadr[self.jid]])

    @property
    def range(self) -> tuple[float, float]:
        lo, hi = self.ctx.model.jnt_range[self.jid]
        return float(lo), float(hi)

    @property
    def axis(self) -> np.ndarray:
        return np.array(self.ctx.data.xaxis[self.jid])

    @property
    def anchor(self) -> np.ndarray:
        return np.array(self.ctx.data.xanchor[self.jid])

    @property
    def body(self) -> int:
        return int(self.ctx.model.jnt_bodyid[self.jid])

    def body_mat(self) -> np.ndarray:
        return np.array(self.ctx.data.xmat[self.body]).reshape(3, 3)

    def body_pos(self) -> np.ndarray:
        return np.array(self.ctx.data.xpos[self.body])

    def geoms(self) -> list[int]:
        """Collision geoms of the moving body (and its children)."""
        m = self.ctx.model
        bodies = set(self.ctx._body_subtrees[self.body])
        return [
            g for g in range(m.ngeom)
            if m.geom_bodyid[g] in bodies and (m.geom_contype[g] != 0 or m.geom_conaffinity[g] != 0)
        ]

    def point_velocity_dir(self, p: np.ndarray, sign: float) -> np.ndarray:
        """Unit direction in which world point ``p`` (on the body) moves when q moves by ``sign``."""
        if self.type == SLIDE:
            v = self.axis * sign
        else:
            v = np.cross(self.axis * sign, p - self.anchor)
        return v / (np.linalg.norm(v) + 1e-9)


def _articulated_owner(ctx: ExpertContext, name: str) -> tuple[object, list[str]]:
    """(LIBERO object holding the open/close thresholds, joint names) for an object or region."""
    env = ctx.sim_env
    if name in env.object_sites_dict:
        site = env.object_sites_dict[name]
        joints = list(getattr(site, "joints", None) or [])
        owner = env.get_object(site.parent_name)
        if not joints:  # e.g. microwave_1_heating_region: the owner's joints
            joints = list(getattr(owner, "joints", None) or [])
        return owner, joints
    owner = env.get_object(name)
    return owner, list(getattr(owner, "joints", None) or [])


def _movable_joints(ctx: ExpertContext, name: str) -> list[JointView]:
    _, joints = _articulated_owner(ctx, name)
    out = []
    for j in joints:
        try:
            jv = JointView(ctx, j)
            if jv.type in (SLIDE, HINGE):
                out.append(jv)
        except Exception:  # noqa: BLE001 - joints not in the model
            continue
    return out


def articulation_ranges(ctx: ExpertContext, name: str) -> dict[str, list[float]]:
    owner, _ = _articulated_owner(ctx, name)
    props = getattr(owner, "object_properties", {}) or {}
    return dict(props.get("articulation", {}) or {})


def articulated_container(ctx: ExpertContext, region: str, relation: str = "in") -> str | None:
    """If ``region`` is a site inside an articulated fixture with open/close semantics,
    return the name to pass to :func:`open_region`; else None.

    A site that moves with its own joint (a drawer region) always counts; a site on the
    fixture's fixed body counts only for ``relation == "in"`` (the microwave's heating
    region is inside, the cabinet's ``top_side`` is on top and never needs opening).
    """
    env = ctx.sim_env
    if region not in env.object_sites_dict:
        return None
    site = env.object_sites_dict[region]
    own_joints = list(getattr(site, "joints", None) or [])
    if not own_joints and relation != "in":
        return None
    rng = articulation_ranges(ctx, region)
    if not rng.get("default_open_ranges"):
        return None
    if not _movable_joints(ctx, region):
        return None
    # a drawer region carries its own joint (its open/close predicates work on the region);
    # a region on the fixed body (microwave heating region) is opened via its parent object
    return region if own_joints else site.parent_name


def _pred(ctx: ExpertContext, op: str, name: str) -> bool:
    try:
        return ctx.check_predicate([op, name])
    except Exception:  # noqa: BLE001
        return False


def is_open(ctx: ExpertContext, name: str) -> bool:
    return _pred(ctx, "open", name)


def is_closed(ctx: ExpertContext, name: str) -> bool:
    return _pred(ctx, "close", name)


def _threshold(ctx: ExpertContext, name: str, which: str) -> float:
    """LIBERO's success threshold for ``which`` (the edge of the success range)."""
    rng = articulation_ranges(ctx, name)
    key = {"open": "default_open_ranges", "close": "default_close_ranges",
           "turnon": "default_turnon_ranges", "turnoff": "default_turnoff_ranges"}[which]
    other = {"open": "default_close_ranges", "close": "default_open_ranges",
             "turnon": "default_turnoff_ranges", "turnoff": "default_turnon_ranges"}[which]
    r, c = rng.get(key), rng.get(other)
    if not r or not c:
        return float("nan")
    return float(min(r) if np.mean(r) > np.mean(c) else max(r))


def _target_q(ctx: ExpertContext, name: str, which: str) -> tuple[float, float]:
    """(target qpos, sign of motion) for ``which`` in open/close/turnon/turnoff.

    Targets are placed well inside the success range, past its threshold.
    """
    rng = articulation_ranges(ctx, name)
    jv = _movable_joints(ctx, name)[0]
    lo, hi = jv.range
    if which == "open":
        r = rng.get("default_open_ranges") or [hi, hi]
        c = rng.get("default_close_ranges") or [lo, lo]
    elif which == "close":
        r = rng.get("default_close_ranges") or [lo, lo]
        c = rng.get("default_open_ranges") or [hi, hi]
    elif which == "turnon":
        r = rng.get("default_turnon_ranges") or [hi, hi]
        c = rng.get("default_turnoff_ranges") or [lo, lo]
    else:
        r = rng.get("default_turnoff_ranges") or [lo, lo]
        c = rng.get("default_turnon_ranges") or [hi, hi]
    sign = 1.0 if np.mean(r) > np.mean(c) else -1.0
    # success threshold = the edge of the success range facing the other state; aim a
    # margin past it (half the range, at most 0.3 rad / 3 cm), never past the joint limit
    thr = min(r) if sign > 0 else max(r)
    width = float(max(r) - min(r))
    margin = min(0.5 * width, 0.3 if jv.type == HINGE else 0.03)
    tgt = thr + sign * margin
    tgt = float(np.clip(tgt, lo, hi))
    jv.threshold = float(thr)  # noqa: B010 - read by _reached
    return float(tgt), sign


_STALL: dict[int, tuple[float, int]] = {}


def _reached(jv: JointView, q_tgt: float, sign: float) -> bool:
    """The joint is at/past ``q_tgt``, or past the success threshold and no longer moving
    (a drawer that is shut stops short of its joint limit)."""
    q = jv.qpos
    if (q - q_tgt) * sign >= 0:
        _STALL.pop(id(jv), None)
        return True
    thr = getattr(jv, "threshold", None)
    if thr is None or (q - thr) * sign <= 0:
        return False
    prev, n = _STALL.get(id(jv), (q, 0))
    n = n + 1 if abs(q - prev) < 2e-4 else 0
    _STALL[id(jv)] = (q, n)
    return n >= 3


# ---------------------------------------------------------------------------- small helpers
def _yaw_for_fingers_along(ctx: ExpertContext, direction: np.ndarray) -> float:
    """Top-down yaw such that the fingers close along the horizontal ``direction``."""
    f = ctx.finger_axis()
    cur = ctx.eef_yaw()
    a_f = np.arctan2(f[1], f[0])
    a_d = np.arctan2(direction[1], direction[0])
    return float(cur + (a_d - a_f))


def _fixture_top(ctx: ExpertContext, name: str) -> float:
    """Top of the articulated fixture that ``name`` (object or region) belongs to."""
    env = ctx.sim_env
    owner = env.object_sites_dict[name].parent_name if name in env.object_sites_dict else name
    return ctx.top_z(owner)


def _set_gripper(ctx: ExpertContext, command: float, steps: int, R: np.ndarray | None = None) -> Iterator[Action]:
    """Drive the gripper for exactly ``steps`` steps (4 steps ~ a full swing) holding pose.

    ``R`` is the orientation to hold (default: the current top-down yaw)."""
    pos = ctx.eef_pos()
    R = target_mat_for(ctx, None) if R is None else R
    for _ in range(steps):
        yield pose_action(ctx, pos, gripper=command, target_mat=R)


def _grip(ctx: ExpertContext, command: float, R: np.ndarray, min_steps: int = 6, max_steps: int = 15) -> Iterator[Action]:
    """Open/close holding position and an arbitrary orientation; stop when the fingers settle."""
    pos = ctx.eef_pos()
    prev = ctx.gripper_opening()
    for k in range(max_steps):
        yield pose_action(ctx, pos, gripper=command, target_mat=R)
        cur = ctx.gripper_opening()
        if k + 1 >= min_steps and abs(cur - prev) < 2e-4:
            break
        prev = cur


def _handle_geom(ctx: ExpertContext, jv: JointView, out_dir: np.ndarray) -> int:
    gs = jv.geoms()
    proj = [float(np.dot(ctx.data.geom_xpos[g], out_dir)) for g in gs]
    return gs[int(np.argmax(proj))]


def _geom_extent_along(ctx: ExpertContext, g: int, d: np.ndarray) -> float:
    """Half-extent of geom ``g``'s local AABB projected on world direction ``d``."""
    R = ctx.data.geom_xmat[g].reshape(3, 3)
    h = ctx.model.geom_aabb[g][3:]
    return float(np.sum(np.abs(R.T @ d) * h))


def _side_grasp_mat(ctx: ExpertContext, approach: np.ndarray) -> np.ndarray:
    """Gripper pointing horizontally along ``approach`` with the fingers closing vertically.

    The grip-site frame has z = approach (towards the fingertips) and x = closing axis; of
    the two mirror solutions take the one nearer the current orientation.
    """
    z = approach / (np.linalg.norm(approach) + 1e-9)
    best, best_ang = None, np.inf
    cur = ctx.eef_mat()
    for sx in (1.0, -1.0):
        x = np.array([0.0, 0.0, sx])
        y = np.cross(z, x)
        R = np.stack([x, y, z], axis=1)
        ang = np.arccos(np.clip((np.trace(R @ cur.T) - 1) / 2, -1, 1))
        if ang < best_ang:
            best, best_ang = R, ang
    return best


def _servo(ctx: ExpertContext, pos: np.ndarray, R: np.ndarray, gripper: float, tol: float, max_steps: int,
           max_speed: float = 1.0, rot_tol: float = 0.06, settle: int = 0) -> Iterator[Action]:
    """move_to with an arbitrary target orientation matrix."""
    from .motion import _rot_error

    for _ in range(max_steps):
        if np.linalg.norm(pos - ctx.eef_pos()) < tol and np.linalg.norm(_rot_error(ctx, R)) < rot_tol:
            break
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R, max_speed=max_speed)
    for _ in range(settle):
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R, max_speed=max_speed)


def _rotate_smoothly(ctx: ExpertContext, pos: np.ndarray, R_goal: np.ndarray, gripper: float,
                     max_rate: float = 0.25, max_steps: int = 25, done_ang: float = 0.2) -> Iterator[Action]:
    """Servo to ``pos`` while turning to ``R_goal`` along the geodesic, at most ``max_rate``
    rad of new target per step (one large rotation command makes the OSC flail)."""
    from .motion import _rot_error

    for _ in range(max_steps):
        err = _rot_error(ctx, R_goal)
        ang = float(np.linalg.norm(err))
        if ang < done_ang and np.linalg.norm(pos - ctx.eef_pos()) < 0.03:
            break
        R_t = R_goal if ang < 1e-6 else _rot(err / ang, min(ang, max_rate)) @ ctx.eef_mat()
        yield pose_action(ctx, pos, gripper=gripper, target_mat=R_t)


def _pull_drawer(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Side grasp of the drawer handle (gripper horizontal, fingers above/below the bar), pull.

    A top-down grasp does not fit: the Panda hand is ~20 cm wide along the closing axis and
    would hit the cabinet front/top; approaching along the slide axis keeps it in free space.
    """
    out = jv.axis * sign  # direction the handle moves when opening
    out[2] = 0.0
    out /= np.linalg.norm(out) + 1e-9
    g = _handle_geom(ctx, jv, out)
    h = np.array(ctx.data.geom_xpos[g])
    half = _geom_extent_along(ctx, g, out)
    R_start, pos_start = ctx.eef_mat(), ctx.eef_pos()
    R = _side_grasp_mat(ctx, -out)
    grasp = h + out * (half * 0.2)
    pre = grasp + out * 0.10
    high = pre.copy()
    high[2] = max(pre[2], ctx.eef_pos()[2])
    if _DEBUG:
        print("handle", h.round(4), "grasp", grasp.round(4), "R", R.round(2).tolist())
    yield from _grip(ctx, GRIP_OPEN, ctx.eef_mat(), min_steps=1)
    yield from _rotate_smoothly(ctx, high, R, GRIP_OPEN, max_rate=0.3, max_steps=40, done_ang=0.3)
    yield from _servo(ctx, pre, R, GRIP_OPEN, tol=0.008, max_steps=50)
    yield from _servo(ctx, grasp, R, GRIP_OPEN, tol=0.005, max_steps=40, max_speed=0.6, settle=1)
    yield from _grip(ctx, GRIP_CLOSE, R)
    # pull along the slide axis until the joint passes the target
    start_q = jv.qpos
    for k in range(max_steps):
        q = jv.qpos
        if _reached(jv, q_tgt, sign):
            break
        remaining = abs(q_tgt - q) + 0.01
        tgt = ctx.eef_pos() + out * min(0.03, remaining)
        tgt[2] = grasp[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.6)
    # a few steps free the bar (the fingers straddle it vertically and back off along the
    # slide); waiting for the fingers to come to rest would only cost time
    yield from _grip(ctx, GRIP_OPEN, R, min_steps=3, max_steps=6)
    # back off along the slide axis and rise clear of the fixture before turning the wrist
    # back to top-down (the turning hand sweeps ~10 cm around the grip site)
    p = ctx.eef_pos() + out * 0.07
    p[2] = max(p[2] + 0.04, _fixture_top(ctx, name) + 0.03)
    yield from _servo(ctx, p, R, GRIP_OPEN, tol=0.025, max_steps=25)
    # turn back towards the starting orientation while heading back to the start position
    # (nominal arm configuration for whatever comes next)
    mid = 0.5 * (p + pos_start)
    mid[2] = max(p[2], pos_start[2])
    yield from _rotate_smoothly(ctx, mid, R_start, GRIP_OPEN)
    # finish exactly top-down (a residual tilt spoils the next top-down grasp)
    yield from move_to(ctx, ctx.eef_pos(), yaw=None, gripper=GRIP_OPEN, tol=0.03, rot_tol=0.04, max_steps=15)
    return (jv.qpos - start_q) * sign > 0


def _horizontal_push_mat(ctx: ExpertContext, push: np.ndarray, pitch: float = np.pi / 4) -> np.ndarray:
    """Gripper pointing along ``push`` tilted down by ``pitch`` (fingertips lead, the wrist
    and forearm stay up and back), fingers closing horizontally across ``push``."""
    z = push * np.cos(pitch) - np.array([0.0, 0.0, 1.0]) * np.sin(pitch)
    z /= np.linalg.norm(z) + 1e-9
    cur = ctx.eef_mat()
    best, best_ang = None, np.inf
    for sx in (1.0, -1.0):
        x = np.cross(np.array([0.0, 0.0, 1.0]), push) * sx
        x /= np.linalg.norm(x) + 1e-9
        y = np.cross(z, x)
        R = np.stack([x, y, z], axis=1)
        ang = np.arccos(np.clip((np.trace(R @ cur.T) - 1) / 2, -1, 1))
        if ang < best_ang:
            best, best_ang = R, ang
    return best


def _push_drawer(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    """Push the drawer shut with the fingertips of the (closed) horizontal gripper on the
    handle.  A top-down hand would bring the forearm onto the cabinet top when the drawer
    is low and deep; pointing the gripper along the slide keeps the arm back."""
    push = jv.axis * sign  # direction the drawer moves when closing
    push[2] = 0.0
    push /= np.linalg.norm(push) + 1e-9
    g = _handle_geom(ctx, jv, -push)
    h = np.array(ctx.data.geom_xpos[g])
    half = _geom_extent_along(ctx, g, push)
    tip = _fingertip_depth(ctx)
    R_start, pos_start = ctx.eef_mat(), ctx.eef_pos()
    R = _horizontal_push_mat(ctx, push)
    a = R[:, 2]  # approach axis (towards the fingertips)
    start = h - push * (half + 0.012) - a * tip
    pre = start - push * 0.06 + np.array([0, 0, 0.04])
    high = pre.copy()
    high[2] = max(pre[2] + 0.05, ctx.eef_pos()[2])
    yield from _set_gripper(ctx, GRIP_CLOSE, 2)
    yield from _rotate_smoothly(ctx, high, R, GRIP_CLOSE, max_rate=0.3, max_steps=40, done_ang=0.3)
    yield from _servo(ctx, pre, R, GRIP_CLOSE, tol=0.01, max_steps=40)
    yield from _servo(ctx, start, R, GRIP_CLOSE, tol=0.008, max_steps=30, max_speed=0.6)
    start_q = jv.qpos
    for k in range(max_steps):
        q = jv.qpos
        if _reached(jv, q_tgt, sign):
            break
        tgt = ctx.eef_pos() + push * 0.03
        tgt[2] = start[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.7)
    p = ctx.eef_pos() - push * 0.06
    p[2] += 0.04
    yield from _servo(ctx, p, R, GRIP_CLOSE, tol=0.02, max_steps=20)
    mid = 0.5 * (p + pos_start)
    mid[2] = max(p[2], pos_start[2])
    yield from _rotate_smoothly(ctx, mid, R_start, GRIP_CLOSE)
    yield from move_to(ctx, ctx.eef_pos(), yaw=None, gripper=GRIP_OPEN, tol=0.03, rot_tol=0.04, max_steps=15)
    return (jv.qpos - start_q) * sign > 0


# ---------------------------------------------------------------------------- hinged doors
def _door_panel(ctx: ExpertContext, jv: JointView) -> int:
    """The door's biggest collision geom (the panel)."""
    gs = jv.geoms()
    vol = [float(np.prod(ctx.model.geom_aabb[g][3:])) for g in gs]
    return gs[int(np.argmax(vol))]


def _rot(axis: np.ndarray, ang: float) -> np.ndarray:
    """Rotation matrix about a unit ``axis`` by ``ang`` (Rodrigues)."""
    k = axis / (np.linalg.norm(axis) + 1e-12)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * (K @ K)


def _swing_door(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
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
    top = float(c[2] + _geom_extent_along(ctx, g, np.array([0, 0, 1.0])))
    tip = _fingertip_depth(ctx)
    p = c + e_long * (L - d_c) - n * (h[i_thin] + 0.012)
    p[2] = top - 0.022 + tip
    # express in the door body frame so it follows the door
    R0, x0 = jv.body_mat(), jv.body_pos()
    p_local = R0.T @ (p - x0)

    def contact_now() -> np.ndarray:
        return jv.body_pos() + jv.body_mat() @ p_local

    yaw = _yaw_for_fingers_along(ctx, e_long)
    q0 = jv.qpos
    if _DEBUG:
        print("door q", round(q0, 3), "contact", p.round(3), "n", n.round(2), "e_long", e_long.round(2), "top", round(top, 3))
    yield from _set_gripper(ctx, GRIP_CLOSE, 2)
    yield from move_to(ctx, p + np.array([0, 0, 0.10]), yaw=yaw, gripper=GRIP_CLOSE, tol=0.015, max_steps=70)
    yield from move_to(ctx, p, yaw=yaw, gripper=GRIP_CLOSE, tol=0.008, max_steps=40, max_speed=0.6)
    R = target_mat_for(ctx, yaw)
    for k in range(max_steps):
        q = jv.qpos
        if _reached(jv, q_tgt, sign):
            break
        lead = min(0.2, abs(q_tgt - q) + 0.1)
        cur = contact_now()
        tgt = a + _rot(ks, lead) @ (cur - a)
        tgt[2] = p[2]
        yield pose_action(ctx, tgt, gripper=GRIP_CLOSE, target_mat=R, max_speed=0.6)
    # back off from the panel, then up
    back = contact_now() - a
    n_now = np.cross(ks, back)
    n_now /= np.linalg.norm(n_now) + 1e-9
    yield from move_to(ctx, ctx.eef_pos() - n_now * 0.03, gripper=GRIP_CLOSE, tol=0.015, max_steps=12)
    yield from move_to(ctx, ctx.eef_pos() + np.array([0, 0, 0.08]), gripper=GRIP_CLOSE, tol=0.02, max_steps=20)
    return (jv.qpos - q0) * sign > 0


# ---------------------------------------------------------------------------- knobs
def _turn_knob(ctx: ExpertContext, name: str, jv: JointView, q_tgt: float, sign: float, max_steps: int) -> Iterator[Action]:
    gs = jv.geoms()
    tops = [float(ctx.data.geom_xpos[g][2] + _geom_extent_along(ctx, g, np.array([0, 0, 1.0]))) for g in gs]
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
    yaw0 = _yaw_for_fingers_along(ctx, across)
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
    from .context import top_down_mat

    for k in range(max_steps):
        q = jv.qpos
        if _reached(jv, q_tgt, sign):
            break
        # rotate at most ~0.2 rad per step towards the goal yaw
        cur = ctx.eef_yaw()
        dy = float(np.clip((yaw_goal - cur + np.pi) % (2 * np.pi) - np.pi, -0.2, 0.2))
        yield pose_action(ctx, grasp, gripper=GRIP_CLOSE, target_mat=top_down_mat(cur + dy), rot_gain=1.0)
    yield from _grip(ctx, GRIP_OPEN, ctx.eef_mat(), min_steps=3)
    up = grasp + np.array([0, 0, 0.08])
    yield from move_to(ctx, up, yaw=yaw_start, gripper=GRIP_OPEN, tol=0.02, rot_tol=0.15, max_steps=30)
    return (jv.qpos - q0) * sign > 0


# ---------------------------------------------------------------------------- public API
def _drive(ctx: ExpertContext, name: str, which: str, max_steps: int = 120) -> Iterator[Action]:
    joints = _movable_joints(ctx, name)
    if not joints:
        return False
    jv = joints[0]
    q_tgt, sign = _target_q(ctx, name, which)
    jv.threshold = _threshold(ctx, name, which)
    # already there?
    if (jv.qpos - q_tgt) * sign >= -1e-3:
        return True
    if which in ("turnon", "turnoff"):
        return (yield from _turn_knob(ctx, name, jv, q_tgt, sign, max_steps))
    if jv.type == SLIDE:
        if which == "open":
            return (yield from _pull_drawer(ctx, name, jv, q_tgt, sign, max_steps))
        return (yield from _push_drawer(ctx, name, jv, q_tgt, sign, max_steps))
    return (yield from _swing_door(ctx, name, jv, q_tgt, sign, max_steps))


def open_region(ctx: ExpertContext, region: str, max_steps: int = 120) -> Iterator[Action]:
    """Open the drawer/door that ``region`` (or the object ``region``) belongs to."""
    if is_open(ctx, region):
        return True
    return (yield from _drive(ctx, region, "open", max_steps))


def close_region(ctx: ExpertContext, region: str, max_steps: int = 120) -> Iterator[Action]:
    """Close the drawer/door that ``region`` (or the object ``region``) belongs to."""
    if is_closed(ctx, region):
        return True
    return (yield from _drive(ctx, region, "close", max_steps))


def turn_on(ctx: ExpertContext, obj: str, max_steps: int = 80) -> Iterator[Action]:
    if _pred(ctx, "turnon", obj):
        return True
    return (yield from _drive(ctx, obj, "turnon", max_steps))


def turn_off(ctx: ExpertContext, obj: str, max_steps: int = 80) -> Iterator[Action]:
    if _pred(ctx, "turnoff", obj):
        return True
    return (yield from _drive(ctx, obj, "turnoff", max_steps))


def _fingertip_depth(ctx: ExpertContext) -> float:
    """How far the lowest finger point sits below the grip site (top-down gripper)."""
    g = ctx.robot.gripper
    lows = []
    for key in ("left_finger", "right_finger"):
        for n in g.important_geoms[key]:
            gid = ctx.model.geom_name2id(n)
            lows.append(ctx.data.geom_xpos[gid][2] - _geom_extent_along(ctx, gid, np.array([0, 0, 1.0])))
    return float(ctx.eef_pos()[2] - min(lows))


__all__ = [
    "open_region", "close_region", "turn_on", "turn_off",
    "articulated_container", "ensure_accessible", "is_open", "is_closed", "opened_boxes", "JointView",
]


# ---------------------------------------------------------------------------- planner rules
def opened_boxes(ctx: ExpertContext, name: str) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """World AABBs (lo, hi), one per collision geom, the moving part of a *drawer* will
    occupy once opened.

    The drawer's collision geoms shifted along the slide axis by the distance still to go;
    None for anything but a closed slide joint (doors swing, nothing to predict here).
    """
    joints = _movable_joints(ctx, name)
    if not joints or joints[0].type != SLIDE:
        return None
    jv = joints[0]
    q_tgt, _ = _target_q(ctx, name, "open")
    shift = jv.axis * (q_tgt - jv.qpos)
    boxes = []
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    # per geom: one box around drawer + handle would swell the keep-out by the handle's reach
    for g in jv.geoms():
        c, h = ctx.model.geom_aabb[g][:3], ctx.model.geom_aabb[g][3:]
        R = ctx.data.geom_xmat[g].reshape(3, 3)
        pts = ctx.data.geom_xpos[g] + (c + signs * h) @ R.T + shift
        boxes.append((pts.min(0), pts.max(0)))
    return boxes or None


def ensure_accessible(ctx: ExpertContext, region: str, relation: str = "in",
                      obj: str | None = None) -> Iterator[Action]:
    """Precondition for 'in'/'on' targets: a region inside a closed articulated container
    (a drawer region, the microwave's heating region) is opened first.

    If ``obj`` (the thing to put there) stands where the opened drawer will overhang it, it
    is moved aside first: once the drawer is out, no top-down grasp of it fits (the hand
    would have to come down through the drawer), while with the drawer shut it is free.
    """
    try:
        cont = articulated_container(ctx, region, relation)
    except Exception:  # noqa: BLE001 - not an articulated site
        cont = None
    if cont is not None and not is_open(ctx, cont):
        boxes = opened_boxes(ctx, cont) if obj is not None else None
        if boxes:
            from .pick_place import clear_of_boxes  # pick_place does not import this module

            yield from clear_of_boxes(ctx, obj, boxes)
        yield from open_region(ctx, cont)
    return True
