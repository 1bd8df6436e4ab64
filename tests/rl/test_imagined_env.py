"""The vectorised imagined environment: reset from contexts, chunked steps, termination at eta
and at the horizon, rewards frozen at t_end, mixed-task batches."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.kinematics import NextStateModel, PinholeCamera
from worldenv_core.models.worldsim import WorldSimulator
from worldenv_core.imagination.env import Context, ImaginedEnv

TINY = dict(image_size=32, chunk=4, memory_offsets=(0, 2), latent_size=8, latent_channels=4, ae_widths=(8, 16),
            width=16, map_channels=4, use_raw_actions=True, sampling_steps=1)
REFLECTOR = {"_target_": "worldenv_core.models.reflector.Reflector", "camera": "agentview", "input_size": None,
             "max_frames": 8, "d_model": 16, "layers": 1, "heads": 2, "instruction_dim": 16,
             "frame_encoder": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                               "cond_dim": 16, "widths": [8, 8], "keypoints": 4}}


def camera(z):
    # looking down -z from above the table at height z
    return PinholeCamera("agentview", 32, 30.0, np.array([0.0, 0.0, z]), np.eye(3))


def make_env(eta, horizon=12):
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
    return ImaginedEnv(sim, {0: camera(2.0), 3: camera(2.5)}, instantiate(REFLECTOR), encoder, eta, horizon)


def contexts():
    g = torch.Generator().manual_seed(0)
    return [Context(task_id=t, instruction=f"task {t}", frame=torch.randint(0, 255, (3, 32, 32), generator=g,
                                                                             dtype=torch.uint8),
                    proprio=torch.tensor([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0])) for t in (0, 3, 0)]


def test_rollouts_run_to_the_horizon_when_the_reflector_never_fires():
    env = make_env(eta=1.0, horizon=12)  # R < 1: only the horizon ends a rollout
    s = env.reset(contexts())
    assert s.frames.shape == (3, 3, 32, 32) and not s.done.any()
    for _ in range(2):
        s = env.step(torch.zeros(3, 4, 7))
        assert not s.done.any()
    s = env.step(torch.zeros(3, 4, 7))
    assert s.done.all() and (s.t == 12).all() and not s.by_reflector.any()
    assert ((s.reward > 0) & (s.reward < 1)).all()


def test_a_rollout_stops_exactly_when_r_exceeds_eta_and_its_reward_is_frozen():
    env = make_env(eta=0.0)  # R > 0 after the first chunk: every rollout stops there
    env.reset(contexts())
    first = env.step(torch.zeros(3, 4, 7))
    assert first.done.all() and first.by_reflector.all() and (first.t == 4).all()
    later = env.step(torch.ones(3, 4, 7))
    assert torch.equal(later.reward, first.reward) and (later.t == 4).all()
    assert torch.equal(later.frames, first.frames) and torch.equal(later.proprio, first.proprio)


def test_eta_between_scores_stops_only_the_rollouts_above_it():
    env = make_env(eta=0.5)
    env.reset(contexts())
    env.step(torch.zeros(3, 4, 7), generator=torch.Generator().manual_seed(1))
    scores = env.scorer.score()
    env.eta = float(scores.median())  # one above, one at (not above), one below
    env.reset(contexts())
    s = env.step(torch.zeros(3, 4, 7), generator=torch.Generator().manual_seed(1))  # the same imagined frames
    assert s.done.tolist() == (scores > env.eta).tolist() and s.done.sum() == 1


def test_unknown_task_and_bad_eta_are_clear_errors():
    env = make_env(eta=0.5)
    bad = contexts()
    bad[0].task_id = 7
    with pytest.raises(ValueError, match=r"no camera for task\(s\) \[7\]"):
        env.reset(bad)
    with pytest.raises(ValueError, match=r"eta .* must be in \[0, 1\]"):
        make_env(eta=2.0)
