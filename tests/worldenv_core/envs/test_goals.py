"""A goal's `On` predicate measured in the real LIBERO simulator agrees with the oracle on either side of its 3 cm."""
import numpy as np
import pytest

from worldenv_core.envs.goals import ON_TOLERANCE_M, on_offsets
from worldenv_core.envs.libero_env import LiberoEnv

pytestmark = pytest.mark.sim


def set_down(env, obj: str, target: str, dx: float) -> None:
    """Drop `obj` from 3 cm above `target`, `dx` off its centre, and let it settle (the arm holds still)."""
    raw = env.raw.env
    sim = raw.sim
    start, _ = sim.model.get_joint_qpos_addr(raw.get_object(obj).joints[0])
    sim.data.qpos[start:start + 3] = sim.data.body_xpos[raw.obj_body_id[target]] + np.array([dx, 0.0, 0.03])
    sim.data.qpos[start + 3:start + 7] = [1.0, 0.0, 0.0, 0.0]
    sim.data.qvel[:] = 0.0
    sim.forward()
    for _ in range(20):
        env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))


def test_the_bowl_set_down_near_and_far_from_the_plates_centre():
    env = LiberoEnv("libero_spatial", 0, render=False)
    try:
        env.reset(0)
        (goal,) = on_offsets(env)  # pick up the black bowl ... and place it on the plate
        assert (goal.obj, goal.target) == ("akita_black_bowl_1", "plate_1")
        assert not goal.contact and not goal.holds and not goal.off_centre  # where the benchmark puts it
        for dx, success in ((0.01, True), (0.05, False)):  # the second lifts the bowl off the plate and sets it down again
            set_down(env, goal.obj, goal.target, dx)
            (goal,) = on_offsets(env)
            assert goal.contact and goal.above and goal.offset_m == pytest.approx(dx, abs=0.005)
            assert goal.holds == env.check_success() == success
            assert goal.off_centre == (not success) and (goal.offset_m >= ON_TOLERANCE_M) == (not success)
    finally:
        env.close()


def test_a_goal_on_a_region_is_not_measured():
    env = LiberoEnv("libero_goal", 1, render=False)  # put the bowl on the stove: the stove's cook region, not a body
    try:
        env.reset(0)
        assert "stove" in env.instruction and on_offsets(env) == []
    finally:
        env.close()
