"""The vectorised imagined environment: reset from contexts, chunked steps, termination at eta
and at the horizon, rewards frozen at t_end, mixed-task batches."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from worldenv_core.errors import ConfigError
from worldenv_core.imagination.env import Context, check_horizon, history_frames, mid_episode_frames


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


def test_a_mid_episode_context_carries_its_recorded_past_at_the_chunk_spacing():
    images = np.arange(30, dtype=np.uint8)[:, None, None, None] * np.ones((1, 2, 2, 3), np.uint8)
    assert history_frames(images, 21, 4)[:, 0, 0, 0].tolist() == [1, 5, 9, 13, 17]  # oldest first, 4 apart
    assert history_frames(images, 3, 4) is None and history_frames(images, 21, 0) is None

    ep = SimpleNamespace(images={"agentview": images}, proprio=np.zeros((30, 7)),  # what from_episode reads
                         meta=SimpleNamespace(task_id=0, instruction="task 0"))

    c = Context.from_episode(ep, "agentview", 8, history_every=4)
    assert c.history.shape == (2, 3, 2, 2) and c.history[:, 0, 0, 0].tolist() == [0, 4] and int(c.frame[0, 0, 0]) == 8
    assert Context.from_episode(ep, "agentview", 8).history is None


def test_the_reflector_scores_each_rollout_with_its_contexts_recorded_past(make_env, contexts):
    """The imagined rollouts' R(o_{1:t}, g) counts the recorded frames before a mid-episode context, each context
    its own: the same as the reflector's score of that whole video from scratch."""
    env = make_env(eta=1.0)
    made = contexts()
    g = torch.Generator().manual_seed(3)
    made[0].history = torch.randint(0, 255, (3, 3, 32, 32), generator=g, dtype=torch.uint8)
    made[2].history = torch.randint(0, 255, (1, 3, 32, 32), generator=g, dtype=torch.uint8)
    s = env.reset(made)
    plain = make_env(eta=1.0).reset(contexts())
    for b, c in enumerate(made):
        video = c.frame[None] if c.history is None else torch.cat([c.history, c.frame[None]])
        assert torch.allclose(s.reward[b], env.reflector.score_video(video, env.encoder([c.instruction])[0]), atol=1e-5)
    assert torch.allclose(s.reward[1], plain.reward[1], atol=1e-6) and not torch.allclose(s.reward[0], plain.reward[0])
    s = env.step(torch.zeros(3, 4, 7))
    assert s.reward.shape == (3,) and ((s.reward > 0) & (s.reward < 1)).all()


def test_a_horizon_that_ends_before_the_reflector_could_call_a_success_is_refused():
    check_horizon(16, label_delay=8, chunk=8)  # a success in the first chunk is seen at the second check
    check_horizon(220, label_delay=8, chunk=8)
    with pytest.raises(ConfigError, match="horizon of 8 steps is shorter than the reflector's label delay .8. plus a "
                                          "chunk .8.*at least 16"):
        check_horizon(8, label_delay=8, chunk=8)
