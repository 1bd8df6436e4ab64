"""Physics substeps split around the controller, as MuJoCo splits `mj_step` for exactly this.

robosuite's step loop runs, in each physics substep (a libero step: 25 of them, 20 Hz control on 2 ms physics),
`sim.forward()` (every stage of mj_forward, with the previous substep's control), the robot's controllers (the
arm's OSC reads the mass matrix, Jacobians and bias forces, and calls `sim.forward()` once more before it does;
they set the control), then `sim.step()` = mj_step, whose own mj_forward computes every stage again. MuJoCo's
mj_step1 is the position and velocity stages (kinematics, collisions, mass matrix, bias forces, sensors: all a
controller reads) and mj_step2 the rest (actuation, acceleration, constraints, integration), for callers that set
the control in between. Inside `LiberoEnv.step` the first forward of a substep is mj_step1, a repeat before the step
does nothing, and the step is mj_step2: the same stages on the same inputs in the same order (the constraint
solver's warm start is saved only when a step integrates), so states, observations and renders are bit for bit
robosuite's own loop (`tests/worldenv_core/envs/test_substeps.py`), with one pass of the stages per substep where
there were three. Euler and implicit integrators only: RK4 runs its own stages (refused below).
"""

from __future__ import annotations

import contextlib

import mujoco


class SplitSubsteps:
    """`with SplitSubsteps(raw):` - `raw` a robosuite env; its `sim.forward` / `sim.step` split while inside."""

    def __init__(self, raw):
        sim = raw.sim
        self.sim, self.model, self.data = sim, sim.model._model, sim.data._data
        if self.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
            raise ValueError("SplitSubsteps needs an integrator mj_step2 runs (Euler or implicit), not RK4")
        self.pending = False  # mj_step1 ran and no step has integrated since: the stages are current

    def forward(self) -> None:
        if not self.pending:
            mujoco.mj_step1(self.model, self.data)
            self.pending = True

    def step(self, with_udd: bool = True) -> None:
        if not self.pending:  # a step nothing forwarded first: robosuite's own meaning
            mujoco.mj_step(self.model, self.data)
            return
        mujoco.mj_step2(self.model, self.data)
        self.pending = False

    def __enter__(self):
        self.pending = False
        self.sim.forward, self.sim.step = self.forward, self.step  # instance attributes shadow MjSim's methods
        return self

    def __exit__(self, *exc):
        with contextlib.suppress(AttributeError):
            del self.sim.forward, self.sim.step
        if self.pending:  # left between a forward and its step (an error in a controller): finish the stages
            mujoco.mj_forward(self.model, self.data)
            self.pending = False
