"""How far a LIBERO scene is from its goal's `On` predicates, in the simulator's own terms.

LIBERO's `On(a, b)` (`check_ontop` of b) holds when a touches b, a's body origin is not below b's, and their origins
lie within 3 cm of each other in the horizontal plane. So a bowl set down on the plate 4 cm from its centre fails
the oracle while a camera at the reward model's 64 px sees it where a success puts it (a couple of pixels apart):
`analysis.failure_modes --final-state` counts such endings apart from the object lost on the way.

Only object-on-object goals are measured (both names have bodies); a goal on a region (a stove's cook region, a
cabinet's top) is left out (`on_offsets` returns nothing for it)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ON_TOLERANCE_M = 0.03  # LIBERO's `check_ontop`: the horizontal distance under which `On` can hold


@dataclass(frozen=True)
class OnOffset:
    """One `On(obj, target)` goal in the current state."""
    obj: str
    target: str
    contact: bool      # obj touches target
    above: bool        # obj's origin is not below target's
    offset_m: float    # horizontal distance between their origins

    @property
    def holds(self) -> bool:
        """LIBERO's own verdict on this predicate."""
        return self.contact and self.above and self.offset_m < ON_TOLERANCE_M

    @property
    def off_centre(self) -> bool:
        """Set down on the target, but too far from its centre for the oracle."""
        return self.contact and self.above and self.offset_m >= ON_TOLERANCE_M


def on_offsets(env) -> list[OnOffset]:
    """The `On` goals of a `LiberoEnv`'s task in its current simulator state."""
    raw = env.raw.env
    bodies = raw.obj_body_id
    out = []
    for predicate in raw.parsed_problem["goal_state"]:
        if predicate[0].lower() != "on" or len(predicate) != 3:
            continue
        obj, target = predicate[1], predicate[2]
        if obj not in bodies or target not in bodies:
            continue  # a region of a fixture, not a body: not measured here
        p_obj = raw.sim.data.body_xpos[bodies[obj]]
        p_target = raw.sim.data.body_xpos[bodies[target]]
        out.append(OnOffset(obj, target,
                            contact=bool(raw.check_contact(raw.get_object(obj), raw.get_object(target))),
                            above=bool(p_target[2] <= p_obj[2]),
                            offset_m=float(np.linalg.norm(p_obj[:2] - p_target[:2]))))
    return out
