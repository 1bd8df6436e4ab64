import numpy as np
import pytest

from worldenv_core.envs.recording import attempt_seed, rollout, to_episode

pytestmark = pytest.mark.sim


def test_a_simulator_failure_marks_the_episode_failed_without_raising(tiny_env):
    first = tiny_env.reset(init_state=0)

    def act(frame, t):
        return np.full(7, np.nan) if t == 3 else np.r_[0.2, 0, 0, 0, 0, 0, -1.0]

    traj = rollout(tiny_env, act, first, max_steps=10)
    assert traj.error and "non-finite" in traj.error
    assert not traj.success and traj.length == 3 and len(traj.frames) == 4


def test_rollout_logs_policy_extras_and_renders_only_when_kept(tiny_env):
    first = tiny_env.reset(init_state=1)
    traj = rollout(tiny_env, lambda f, t: (np.r_[0, 0, 0.5, 0, 0, 0, -1.0], {"mu": np.ones(7), "beta": -np.ones(7)}),
                   first, max_steps=4)
    assert traj.error is None and traj.length == 4
    assert all(not f.images for f in traj.frames), "stepping must not render"
    ep = to_episode(tiny_env, traj, init_state_index=1, seed=0, source="policy")
    assert ep.step_extras["mu"].shape == (4, 7) and ep.step_extras["beta"].dtype == np.float32
    assert ep.images["agentview"].shape == (5, 64, 64, 3)
    assert ep.images["robot0_eye_in_hand"].shape == (5, 64, 64, 3)
    assert np.array_equal(ep.sim_state[0], first.sim_state)


def test_attempt_seeds_are_distinct_and_stable():
    seeds = {attempt_seed(0, "libero_goal", t, k, a) for t in range(3) for k in range(3) for a in range(3)}
    assert len(seeds) == 27
    assert attempt_seed(0, "libero_goal", 1, 2, 3) == attempt_seed(0, "libero_goal", 1, 2, 3)
    assert attempt_seed(0, "libero_goal", 1, 2, 3) != attempt_seed(1, "libero_goal", 1, 2, 3)
