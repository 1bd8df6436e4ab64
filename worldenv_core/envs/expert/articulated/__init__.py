"""Articulated-object skills for the scripted expert: drawers, doors, knobs.

All skills are generators yielding 7-D OSC_POSE actions (see :mod:`..motion`).  They read the
articulation straight from MuJoCo (joint type, axis, anchor, current qpos, the collision geoms
of the moving body) and the open/close/turn-on thresholds from the LIBERO object class
(``object_properties["articulation"]``), so one rule serves every instance.  This module
dispatches a goal to the skill for the joint's kind:

* :mod:`.joints`: joint discovery, predicates, thresholds and targets, planner queries;
* :mod:`.drawer`: slide joints, pulled open with a side grasp, pushed shut with the fingertips;
* :mod:`.door`: hinges with a panel (microwave), the panel pushed along its arc;
* :mod:`.knob`: hinges with turn-on ranges (stove), grasped from above and twisted.

Pushing a dish onto a table region lives in :mod:`..push`.

Success thresholds come from the LIBERO object (e.g. drawer open iff q < -0.14, stove on iff
q >= 0.5); each skill drives its joint a margin past the threshold and stops when it is there
or when it is past the threshold and has stopped moving (a shut drawer).

Public API::

    open_region(ctx, region)   close_region(ctx, region)      # region or object name
    turn_on(ctx, obj)          turn_off(ctx, obj)
    articulated_container(ctx, region, relation) -> what to open before 'in' (or None)
    ensure_accessible(ctx, region, relation, obj) # planner precondition (+ make room for obj)
    opened_boxes(ctx, drawer) -> where the drawer's geoms will be once open
    is_open(ctx, name) / is_closed(ctx, name)
"""
from __future__ import annotations

from typing import Iterator

from ..context import ExpertContext
from ..motion import Action
from .door import swing_door
from .drawer import pull_drawer, push_drawer
from .joints import (
    SLIDE, JointView, articulated_container, articulation_ranges, is_closed, is_open, movable_joints,
    opened_boxes, predicate, success_threshold, target_q,
)
from .knob import turn_knob

__all__ = [
    "open_region", "close_region", "turn_on", "turn_off",
    "articulated_container", "ensure_accessible", "is_open", "is_closed", "opened_boxes", "JointView",
    "articulation_ranges", "target_q",
]


def _drive(ctx: ExpertContext, name: str, which: str, max_steps: int = 120) -> Iterator[Action]:
    """Drive the first movable joint of ``name`` for ``which`` (open/close/turnon/turnoff)."""
    joints = movable_joints(ctx, name)
    if not joints:
        return False
    jv = joints[0]
    q_tgt, sign = target_q(ctx, name, which)
    jv.threshold = success_threshold(ctx, name, which)
    # already there?
    if (jv.qpos - q_tgt) * sign >= -1e-3:
        return True
    if which in ("turnon", "turnoff"):
        return (yield from turn_knob(ctx, name, jv, q_tgt, sign, max_steps))
    if jv.type == SLIDE:
        if which == "open":
            return (yield from pull_drawer(ctx, name, jv, q_tgt, sign, max_steps))
        return (yield from push_drawer(ctx, name, jv, q_tgt, sign, max_steps))
    return (yield from swing_door(ctx, name, jv, q_tgt, sign, max_steps))


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
    if predicate(ctx, "turnon", obj):
        return True
    return (yield from _drive(ctx, obj, "turnon", max_steps))


def turn_off(ctx: ExpertContext, obj: str, max_steps: int = 80) -> Iterator[Action]:
    if predicate(ctx, "turnoff", obj):
        return True
    return (yield from _drive(ctx, obj, "turnoff", max_steps))


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
            from ..pick_place import clear_of_boxes  # pick_place does not import this package

            yield from clear_of_boxes(ctx, obj, boxes)
        yield from open_region(ctx, cont)
    return True
