"""What the articulated skills know about a fixture's joint, read live from MuJoCo and LIBERO.

* :class:`JointView`: one joint's type, axis, anchor, qpos, range and moving collision geoms;
* joint discovery for an object or region (:func:`movable_joints`) and its LIBERO
  articulation ranges (``object_properties["articulation"]``);
* the goal predicates (:func:`is_open`, :func:`is_closed`, :func:`predicate`);
* success thresholds and drive targets (:func:`success_threshold`, :func:`target_q`) and the
  stop rule (:func:`reached`);
* planner queries: which container to open before an ``in`` (:func:`articulated_container`)
  and where an opened drawer will be (:func:`opened_boxes`).

Nothing here yields actions; the skills live in :mod:`.drawer`, :mod:`.door`, :mod:`.knob`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..context import ExpertContext

SLIDE, HINGE = 2, 3  # mujoco joint types


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


# ---------------------------------------------------------------------------- discovery
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


def movable_joints(ctx: ExpertContext, name: str) -> list[JointView]:
    """The slide/hinge joints that move ``name`` (an object or region); the first is driven."""
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


def fixture_top(ctx: ExpertContext, name: str) -> float:
    """Top of the articulated fixture that ``name`` (object or region) belongs to."""
    env = ctx.sim_env
    owner = env.object_sites_dict[name].parent_name if name in env.object_sites_dict else name
    return ctx.top_z(owner)


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
    if not movable_joints(ctx, region):
        return None
    # a drawer region carries its own joint (its open/close predicates work on the region);
    # a region on the fixed body (microwave heating region) is opened via its parent object
    return region if own_joints else site.parent_name


# ---------------------------------------------------------------------------- predicates
def predicate(ctx: ExpertContext, op: str, name: str) -> bool:
    """LIBERO's ``op`` predicate on ``name``; False where the checker cannot evaluate it."""
    try:
        return ctx.check_predicate([op, name])
    except Exception:  # noqa: BLE001
        return False


def is_open(ctx: ExpertContext, name: str) -> bool:
    return predicate(ctx, "open", name)


def is_closed(ctx: ExpertContext, name: str) -> bool:
    return predicate(ctx, "close", name)


# ---------------------------------------------------------------------------- targets
def success_threshold(ctx: ExpertContext, name: str, which: str) -> float:
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


def target_q(ctx: ExpertContext, name: str, which: str) -> tuple[float, float]:
    """(target qpos, sign of motion) for ``which`` in open/close/turnon/turnoff.

    Targets are placed well inside the success range, past its threshold.
    """
    rng = articulation_ranges(ctx, name)
    jv = movable_joints(ctx, name)[0]
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
    jv.threshold = float(thr)  # noqa: B010 - read by reached
    return float(tgt), sign


# stall counters per JointView (by id): a shut drawer stops short of its target
_STALL: dict[int, tuple[float, int]] = {}


def reached(jv: JointView, q_tgt: float, sign: float) -> bool:
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


# ---------------------------------------------------------------------------- planner rules
def opened_boxes(ctx: ExpertContext, name: str) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """World AABBs (lo, hi), one per collision geom, the moving part of a *drawer* will
    occupy once opened.

    The drawer's collision geoms shifted along the slide axis by the distance still to go;
    None for anything but a closed slide joint (doors swing, nothing to predict here).
    """
    joints = movable_joints(ctx, name)
    if not joints or joints[0].type != SLIDE:
        return None
    jv = joints[0]
    q_tgt, _ = target_q(ctx, name, "open")
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
