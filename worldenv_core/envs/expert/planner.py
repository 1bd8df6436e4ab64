"""Turn a BDDL goal (``parsed_problem["goal_state"]``) into a chain of skill generators.

Each goal predicate is dispatched through :data:`PREDICATE_HANDLERS`, a plain dict from the
(lower-case) predicate name to ``handler(ctx, *args) -> Iterator[np.ndarray]``.  To support
a new predicate, add an entry (e.g. ``PREDICATE_HANDLERS["open"] = open_articulated``);
nothing else needs to change.  Multi-predicate goals (libero_10) run in order; a predicate
that already holds when its turn comes is skipped, so goals partly satisfied at init cost
nothing.
"""
from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from . import motion as M
from .context import ExpertContext
from .pick_place import pick_and_place_in, pick_and_place_on

Handler = Callable[..., Iterator[np.ndarray]]

PREDICATE_HANDLERS: dict[str, Handler] = {
    "on": pick_and_place_on,
    "in": pick_and_place_in,
}

# Articulated skills (open/close/turnon/turnoff, push) come from .articulated.
from .articulated import (  # noqa: E402
    close_region, ensure_accessible, open_region, turn_off, turn_on,
)
from .push import on_or_push  # noqa: E402

PREDICATE_HANDLERS.update({
    "open": open_region,
    "close": close_region,
    "turnon": turn_on,
    "turnoff": turn_off,
    # a dish onto a table region is pushed; everything else is picked and placed
    "on": on_or_push(pick_and_place_on),
})


def order_goals(ctx: ExpertContext, goals: list[list[str]]) -> list[list[str]]:
    """Order predicates so that enabling ones run first.

    Opening a container must precede putting something in it, and putting something in
    must precede closing it; everything else keeps its BDDL order.
    """
    rank = {"open": 0, "turnon": 2, "turnoff": 2, "close": 3}
    return sorted(goals, key=lambda g: rank.get(g[0].lower(), 1))


def plan(ctx: ExpertContext, goals: list[list[str]] | None = None) -> Iterator[np.ndarray]:
    """Generator over the whole episode: every unmet goal predicate in turn, then a short hold."""
    goals = ctx.goal_state if goals is None else goals
    # Some init states leave objects hovering (a bowl in a drawer starts ~9 cm up and
    # falls); velocities are zero at t=0, so always wait a few steps, then until at rest.
    for k in range(15):
        if k >= 4 and ctx.max_object_speed() < 0.02:
            break
        yield M.make_action(gripper=M.GRIP_OPEN)
    for pred in order_goals(ctx, [list(g) for g in goals]):
        name, args = pred[0].lower(), pred[1:]
        handler = PREDICATE_HANDLERS.get(name)
        if handler is None:
            raise NotImplementedError(f"no expert handler for predicate {pred!r}")
        try:
            if ctx.check_predicate(pred):
                continue
        except Exception:  # checker may not support this predicate: just execute
            pass
        if name in ("in", "on") and len(args) == 2:
            # precondition: a target region inside a closed drawer/door -> open it first
            yield from ensure_accessible(ctx, args[1], name, obj=args[0])
        yield from handler(ctx, *args)
    # let released objects settle before the caller evaluates success
    yield from M.hold(ctx, 5, gripper=M.GRIP_OPEN)
