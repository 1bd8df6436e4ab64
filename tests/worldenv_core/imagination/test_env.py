"""The vectorised imagined environment: reset from contexts, chunked steps, termination at eta
and at the horizon, rewards frozen at t_end, mixed-task batches."""
import numpy as np
import pytest
import torch

from worldenv_core.imagination.env import mid_episode_frames


def test_rollouts_run_to_the_horizon_when_the_reflector_never_fires(make_env, contexts):
    env = make_env(eta=1.0, horizon=12)  # R < 1: only the horizon ends a rollout
    s = env.reset(contexts())
    assert s.frames.shape == (3, 3, 32, 32) and not s.done.any()
    for _ in range(2):
        s = env.step(torch.zeros(3, 4, 7))
        assert not s.done.any()
    s = env.step(torch.zeros(3, 4, 7))
    assert s.done.all() and (s.t == 12).all() and not s.by_reflector.any()
    assert ((s.reward > 0) & (s.reward < 1)).all()


def test_a_rollout_stops_exactly_when_r_exceeds_eta_and_its_reward_is_frozen(make_env, contexts):
    env = make_env(eta=0.0)  # R > 0 after the first chunk: every rollout stops there
    env.reset(contexts())
    first = env.step(torch.zeros(3, 4, 7))
    assert first.done.all() and first.by_reflector.all() and (first.t == 4).all()
    later = env.step(torch.ones(3, 4, 7))
    assert torch.equal(later.reward, first.reward) and (later.t == 4).all()
    assert torch.equal(later.frames, first.frames) and torch.equal(later.proprio, first.proprio)


def test_eta_between_scores_stops_only_the_rollouts_above_it(make_env, contexts):
    env = make_env(eta=0.5)
    env.reset(contexts())
    env.step(torch.zeros(3, 4, 7), generator=torch.Generator().manual_seed(1))
    scores = env.scorer.score()
    env.eta = float(scores.median())  # one above, one at (not above), one below
    env.reset(contexts())
    s = env.step(torch.zeros(3, 4, 7), generator=torch.Generator().manual_seed(1))  # the same imagined frames
    assert s.done.tolist() == (scores > env.eta).tolist() and s.done.sum() == 1


def test_unknown_task_and_bad_eta_are_clear_errors(make_env, contexts):
    env = make_env(eta=0.5)
    bad = contexts()
    bad[0].task_id = 7
    with pytest.raises(ValueError, match=r"no camera for task\(s\) \[7\]"):
        env.reset(bad)
    with pytest.raises(ValueError, match=r"eta .* must be in \[0, 1\]"):
        make_env(eta=2.0)


def test_mid_episode_frames_lie_before_the_first_success():
    success = np.zeros(31, bool)
    success[21:] = True
    assert mid_episode_frames(success, 30, 2) == [7, 14]
    assert mid_episode_frames(np.zeros(31, bool), 30, 1) == [15]


def test_mid_episode_frames_keep_to_the_depth_asked_for():
    """rl.context_depth: keyframes only where the verdict is faithful, e.g. past a third of the way in."""
    success = np.zeros(31, bool)
    success[21:] = True  # the part before success: frames 0-20
    assert mid_episode_frames(success, 30, 2, (1 / 3, 1.0)) == [12, 16]  # 21 x 5/9, 21 x 7/9
    assert mid_episode_frames(success, 30, 2, (0.0, 1.0)) == mid_episode_frames(success, 30, 2)
    assert all(f >= 15 for f in mid_episode_frames(np.zeros(31, bool), 30, 4, (0.5, 1.0)))
    for bad in ((0.5, 0.5), (-0.1, 1.0), (0.2, 1.5), (0.3,), "deep"):
        with pytest.raises(ValueError, match="context depth"):
            mid_episode_frames(success, 30, 2, bad)
