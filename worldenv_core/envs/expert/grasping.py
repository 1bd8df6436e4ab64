"""Grasp rules per object category.

A rule turns the object's live geometry (privileged: MuJoCo geom boxes, see
:meth:`ExpertContext.footprint`) into a :class:`GraspPlan`: where the grip site must go,
with which yaw, and how to approach.  Rules are chosen by LIBERO category name, never by
task, so the same rule serves every scene containing that kind of object.

* ``center``  -- top-down at the footprint centre, fingers closing across the narrow side.
  Boxes, cans, bottles, cartons.  Flat objects (butter, cream cheese) are pinched just above
  the support.  If the wide palm would hit a neighbour, small wrist turns and shifts along
  the long side are searched (:func:`hand_clearance`).  Anything whose narrow side exceeds
  the gripper stroke falls back to ``rim``.
* ``rim``     -- one finger inside, one outside the wall of an open vessel (bowls, ramekins,
  mugs, plates): the body is wider than the gripper's 8 cm stroke, so a centre grasp cannot
  close on it, but the wall is thin.  The side of the rim is picked for clearance from
  neighbouring objects and reachability.

Yaw convention: ``yaw`` is the world heading of the finger-closing axis (see
``ExpertContext.eef_yaw``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .context import ExpertContext

MAX_OPENING = 0.075  # usable Panda stroke (m); fully open is ~0.08


@dataclass
class GraspPlan:
    pos: np.ndarray         # grip-site target at grasp time (world)
    yaw: float              # finger-closing axis heading
    approach_dz: float      # pre-grasp height above ``pos`` for the final straight descent
    kind: str               # rule name, for logs/debugging


RIM_KEYWORDS = ("bowl", "ramekin", "mug", "cup", "plate", "pot", "pan")
FINGERTIP_BELOW = 0.013  # fingertips reach this far below the grip site (m)
PALM_ABOVE = 0.025       # palm collision box starts this far above the grip site (m)


def rule_for(category: str) -> str:
    c = category.lower()
    if any(k in c for k in RIM_KEYWORDS) and "moka" not in c:
        return "rim"
    return "center"


# ------------------------------------------------------------------ helpers
def _obstacle_names(ctx: ExpertContext, exclude: str) -> list[str]:
    names = [n for n in ctx.sim_env.objects_dict if n != exclude]
    names += [n for n in ctx.sim_env.fixtures_dict
              if n not in ("main_table", "floor", "countertop", "coffee_table", "kitchen_table",
                           "study_table", "living_room_table")]
    return names


def _obstacle_points(ctx: ExpertContext, exclude: str, z_above: float) -> np.ndarray:
    """xy samples of other objects' geom boxes that reach above ``z_above`` (N, 2).

    Per geom, not per object: a cabinet with an open drawer is a few thin walls, not one
    solid block, and the gripper may well fit between them.
    """
    pts = []
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    u = np.linspace(-1, 1, 5)
    grid = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
    for n in _obstacle_names(ctx, exclude):
        try:
            gids = ctx.geom_ids(n)
        except Exception:  # bodies without geoms
            continue
        for g in gids:
            c, h = ctx.model.geom_aabb[g][:3], ctx.model.geom_aabb[g][3:]
            R = ctx.data.geom_xmat[g].reshape(3, 3)
            corners = ctx.data.geom_xpos[g] + (c + signs * h) @ R.T
            if corners[:, 2].max() <= z_above:
                continue
            # sample the geom's box footprint (corners alone miss long thin sides)
            loc = np.concatenate([grid * h[:2], np.zeros((len(grid), 1))], 1) + c
            pts.append((ctx.data.geom_xpos[g] + loc @ R.T)[:, :2])
    return np.concatenate(pts) if pts else np.zeros((0, 2))


# Panda hand footprint around the grip site, in (along finger axis, across) half-extents (m),
# measured from the collision geoms: the palm box, and the open fingers below it.
HAND_HALF = (0.105, 0.037)
FINGERS_HALF = (0.052, 0.015)


def rect_margin(pts: np.ndarray, centre: np.ndarray, yaw: float, half: tuple[float, float]) -> float:
    """Smallest xy margin (m, negative = inside) between points and a rectangle with
    half-extents ``half`` (along ``yaw``, across) centred at ``centre``."""
    if not len(pts):
        return 1.0
    axis = np.array([np.cos(yaw), np.sin(yaw)])
    perp = np.array([-axis[1], axis[0]])
    rel = pts - centre[:2]
    return float(np.maximum(np.abs(rel @ axis) - half[0], np.abs(rel @ perp) - half[1]).min())


def hand_clearance(ctx: ExpertContext, name: str, pos: np.ndarray, yaw: float) -> float:
    """Smallest xy margin (m, negative = collision) between the hand at a grasp pose and
    other objects: the palm against anything taller than its underside, the open fingers
    against anything taller than the fingertips."""
    margin = 1.0
    for z_above, half in ((pos[2] + PALM_ABOVE, HAND_HALF), (pos[2] - FINGERTIP_BELOW, FINGERS_HALF)):
        margin = min(margin, rect_margin(_obstacle_points(ctx, name, z_above=z_above), pos, yaw, half))
    return margin


def _robot_base_xy(ctx: ExpertContext) -> np.ndarray:
    return ctx.body_pos_raw(ctx.robot.robot_model.root_body)[:2]


# ------------------------------------------------------------------ rules
def center_grasp(ctx: ExpertContext, name: str, jitter: float = 0.0) -> GraspPlan:
    centre, half, oyaw = ctx.footprint(name)
    lo, hi = ctx.aabb(name)
    height = hi[2] - lo[2]
    # close across the narrower horizontal side of the footprint
    yaw = oyaw if half[0] <= half[1] else oyaw + np.pi / 2
    # Grip-site geometry of the Panda hand: fingertips reach ~1.3 cm below the grip site
    # and the palm starts ~2.5 cm above it.  Go as deep as the palm allows, but keep the
    # fingertips off the support surface.
    z = max(lo[2] + FINGERTIP_BELOW + 0.003, hi[2] - PALM_ABOVE + 0.003)
    # Search small yaw turns and shifts along the long side for a pose whose palm and
    # fingers clear the neighbours (a can next to a flat box blocks the wide palm).
    long_axis = np.array([np.cos(yaw + np.pi / 2), np.sin(yaw + np.pi / 2)])
    long_half = max(half[0], half[1])
    max_shift = max(0.0, min(0.02, long_half - 0.015))
    best, best_score = None, -np.inf
    for dyaw in (0.0, 0.25, -0.25, 0.5, -0.5):
        for shift in (0.0, max_shift / 2, -max_shift / 2, max_shift, -max_shift):
            p = np.array([centre[0], centre[1], z])
            p[:2] += shift * long_axis
            clear = hand_clearance(ctx, name, p, yaw + dyaw)
            score = min(clear, 0.01) - 0.01 * abs(dyaw) - 0.2 * abs(shift)
            if score > best_score:
                best, best_score = (p, yaw + dyaw), score
            if clear > 0.01 and dyaw == 0.0 and shift == 0.0:
                break  # the plain centre grasp is free: take it
        if best_score >= 0.01 - 1e-9:
            break
    pos, yaw = best
    if jitter:
        pos[:2] += ctx.rng.uniform(-jitter, jitter, 2)
        yaw += ctx.rng.uniform(-0.1, 0.1)
    return GraspPlan(pos=pos, yaw=float(yaw), approach_dz=0.06, kind="center")


def rim_grasp(ctx: ExpertContext, name: str, jitter: float = 0.0) -> GraspPlan:
    centre, half, _ = ctx.footprint(name)
    lo, hi = ctx.aabb(name)
    radius = float(np.mean(half))
    wall_inset = 0.012 if radius < 0.09 else 0.015
    r = radius - wall_inset  # grip site sits over the wall; fingers straddle it
    # lower rims (plates) are pinched lower relative to their height
    z = max(hi[2] - PALM_ABOVE + 0.005, lo[2] + FINGERTIP_BELOW + 0.003)
    # Only geoms reaching above the object's base can hit the fingers; lower ones are what
    # it stands on (table, cabinet top, drawer floor) and must not veto a side.
    obstacles = _obstacle_points(ctx, name, z_above=max(z - FINGERTIP_BELOW - 0.01, lo[2] + 0.005))
    # The palm is ~21 cm long along the closing (here: radial) axis, so it reaches well past
    # the centre; whatever stands above its underside (an open drawer overhanging the
    # object) blocks the straight descent even where the fingers are free.
    palm_obstacles = _obstacle_points(ctx, name, z_above=z + PALM_ABOVE)
    base = _robot_base_xy(ctx)
    to_robot = base - centre
    to_robot /= np.linalg.norm(to_robot) + 1e-9
    best, best_score = None, -np.inf
    for ang in np.linspace(-np.pi, np.pi, 24, endpoint=False):
        d = np.array([np.cos(ang), np.sin(ang)])
        p = centre + d * r
        clear = np.min(np.linalg.norm(obstacles - p, axis=1)) if len(obstacles) else 1.0
        # Sides where the open fingers + palm (~4.5 cm around the grip site) would hit a
        # neighbour are out; among the rest prefer the robot-facing side: the far side of an
        # object is often beyond the Panda's reach at table height, and reaching over the
        # object risks knocking it.
        feasible = clear > 0.045
        palm_free = rect_margin(palm_obstacles, p, ang, HAND_HALF) > 0.005
        score = (10.0 if feasible else 0.0) + (3.0 if palm_free else 0.0) + float(d @ to_robot) \
            + 5.0 * min(clear, 0.08)
        if score > best_score:
            best, best_score = d, score
    d = best
    if jitter:
        ang = np.arctan2(d[1], d[0]) + ctx.rng.uniform(-0.15, 0.15)
        d = np.array([np.cos(ang), np.sin(ang)])
    p = centre + d * r
    return GraspPlan(pos=np.array([p[0], p[1], z]), yaw=float(np.arctan2(d[1], d[0])),
                     approach_dz=0.06, kind="rim")


RULES = {"center": center_grasp, "rim": rim_grasp}


def plan_grasp(ctx: ExpertContext, name: str, jitter: float = 0.0) -> GraspPlan:
    """Grasp plan for object ``name`` using its category's rule."""
    rule = rule_for(ctx.category(name))
    if rule == "center" and 2 * min(ctx.footprint(name)[1]) > MAX_OPENING:
        rule = "rim"  # too wide to close on: take it by its edge
    return RULES[rule](ctx, name, jitter)
