"""Recording imagined rollouts: the policy runs in the imagined env exactly as LOOP does, every
frame decoded, and each rollout becomes an imagined episode with the reflector's scores, up to
its own termination, written so `read_episode` reads it back."""

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.data.mcap_io import read_episode, read_reflector_scores
from worldenv_core.imagination.recording import record_imagined_rollouts, write_imagined_rollouts
from worldenv_core.rl.loop import collect_rollouts


def tiny_policy():
    torch.manual_seed(0)
    return instantiate({"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": ["agentview"], "chunk": 4,
                        "hidden": 32, "instruction_dim": 16,
                        "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone",
                                     "cameras": ["agentview"], "cond_dim": 16, "widths": [8, 8], "keypoints": 4}})


@pytest.fixture
def record(make_env, contexts):
    """Two rollouts from each of two contexts at `eta`, recorded."""
    def run(eta, horizon=12):
        env = make_env(eta, horizon)
        encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
        rollouts = record_imagined_rollouts(tiny_policy(), env, contexts()[:2], 2, encoder, "libero_goal",
                                            {0: "task zero", 3: "task three"}, "agentview", extra={"policy": "p"},
                                            generator=torch.Generator().manual_seed(0))
        return env, encoder, rollouts
    return run


def test_rollouts_to_the_horizon_keep_every_frame_and_the_scores_at_chunk_boundaries(contexts, record):
    env, _, rollouts = record(eta=1.0)
    assert env.decode == "last"  # restored for training
    assert len(rollouts) == 4 and [r.episode.meta.task_id for r in rollouts] == [0, 0, 3, 3]
    for r in rollouts:
        ep = r.episode
        assert ep.length == 12 and ep.images["agentview"].shape == (13, 32, 32, 3)
        assert ep.meta.source == "imagined" and not ep.meta.success and not ep.success.any()
        assert sorted(r.scores) == [0, 4, 8, 12] and r.reward == r.scores[12]
        assert ep.step_extras["mu"].shape == (12, 7) and ep.step_extras["beta"].shape == (12, 7)
        assert ep.meta.task_name in ("task zero", "task three") and ep.meta.extra["policy"] == "p"
    # the first frame is the context's, untouched
    assert np.array_equal(rollouts[2].episode.images["agentview"][0], contexts()[1].frame.permute(1, 2, 0).numpy())


def test_a_reflector_stop_ends_the_episode_there_as_an_imagined_success(tmp_path, record):
    _, _, rollouts = record(eta=0.0)  # R > 0 at the first chunk boundary: every rollout stops at t = 4
    for r in rollouts:
        assert r.by_reflector and r.episode.length == 4 and r.episode.meta.success
        assert r.episode.success.tolist() == [False] * 4 + [True] and sorted(r.scores) == [0, 4]
    paths = write_imagined_rollouts(rollouts, tmp_path, eta=0.0)
    assert [p.name for p in paths][0] == "rollout_00_task00_success.mcap"
    back = read_episode(paths[1])
    assert back.meta.source == "imagined" and back.length == 4
    assert read_reflector_scores(paths[1]) == rollouts[1].scores


def test_recording_samples_the_actions_training_would_with_the_same_noise(contexts, record):
    env, encoder, rollouts = record(eta=1.0)
    batch = collect_rollouts(tiny_policy(), env, contexts()[:2], 2, encoder, generator=torch.Generator().manual_seed(0))
    recorded = torch.stack([torch.from_numpy(r.episode.actions) for r in rollouts])
    policy = tiny_policy()
    assert torch.allclose(recorded, policy.unnormalize_actions(batch.actions.flatten(1, 2)), atol=1e-6)
    assert torch.allclose(torch.tensor([r.reward for r in rollouts]), batch.rewards, atol=1e-6)
