import numpy as np
import pytest

from worldenv_core.envs.recording import attempt_seed, policy_episode, rollout, to_episode

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


class ChunkRunner:
    """A policy's interface (a chunk of 4 actions per boundary), remembering the images it was shown."""

    cameras = ["agentview"]

    def __init__(self):
        self.seen = []

    def act_chunk(self, images, proprio, instruction):
        self.seen.append(images["agentview"].copy())
        a = np.tile(np.r_[0.3, 0.1, 0, 0, 0, 0.2, -1.0], (4, 1)).astype(np.float32)
        return a, a, np.zeros_like(a)


def test_a_policy_episode_keeps_its_boundary_renders_and_the_episode_equals_a_full_replay(tiny_env, monkeypatch):
    """The chunk-boundary frames the policy saw are kept, not rendered again: the recorded episode is pixel for
    pixel the replay of every state, at about one render in four fewer here (chunk 4)."""
    runner = ChunkRunner()
    traj = policy_episode(tiny_env, runner, 0, seed=0, max_steps=10, stop_on_success=False)
    assert sorted(traj.images) == [0, 4, 8] and len(traj.frames) == 11
    assert all(np.array_equal(traj.images[t]["agentview"], seen) for t, seen in zip([0, 4, 8], runner.seen))
    renders = []
    real_render = tiny_env.render
    monkeypatch.setattr(tiny_env, "render", lambda cams=None: renders.append(list(cams)) or real_render(cams))
    ep = to_episode(tiny_env, traj, init_state_index=0, seed=0, source="policy")
    # the wrist camera (not the policy's) is rendered at every frame, the agent view only off the boundaries
    assert renders.count(["robot0_eye_in_hand"]) == 3 and len(renders) == 11
    monkeypatch.undo()
    replay = tiny_env.render_states(ep.sim_state)
    for cam in replay:
        assert np.array_equal(ep.images[cam], replay[cam])


def test_attempt_seeds_are_distinct_and_stable():
    seeds = {attempt_seed(0, "libero_goal", t, k, a) for t in range(3) for k in range(3) for a in range(3)}
    assert len(seeds) == 27
    assert attempt_seed(0, "libero_goal", 1, 2, 3) == attempt_seed(0, "libero_goal", 1, 2, 3)
    assert attempt_seed(0, "libero_goal", 1, 2, 3) != attempt_seed(1, "libero_goal", 1, 2, 3)
