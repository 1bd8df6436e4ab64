"""RLOO advantages and the PPO loss of eq. 5 against hand-computed values."""
import math

import pytest
import torch

from worldenv_core.rl.loop import ppo_loss, rloo_advantages


def test_rloo_baseline_is_the_mean_of_the_other_rollouts():
    rewards = torch.tensor([[1.0, 0.0, 0.5, 0.5], [0.2, 0.2, 0.2, 0.2]])
    adv = rloo_advantages(rewards)
    # context 0: b_0 = (0 + .5 + .5) / 3 = 1/3, b_1 = 2/3, b_2 = b_3 = 0.5
    assert torch.allclose(adv[0], torch.tensor([1 - 1 / 3, 0 - 2 / 3, 0.0, 0.0]))
    assert torch.allclose(adv[1], torch.zeros(4))  # equal rewards: no signal
    assert torch.allclose(adv.sum(-1), torch.zeros(2), atol=1e-6)  # RLOO advantages sum to zero
    with pytest.raises(ValueError, match="at least 2 rollouts"):
        rloo_advantages(torch.ones(3, 1))


def test_ppo_loss_by_hand():
    eps = 0.1
    old = torch.zeros(2, 3)
    new = torch.log(torch.tensor([[1.05, 1.5, 9.0], [0.5, 1.0, 1.0]]))
    mask = torch.tensor([[1, 1, 0], [1, 1, 1]])  # rollout 0 stopped after 2 steps: step 3 is padding
    adv = torch.tensor([2.0, -1.0])
    loss, stats = ppo_loss(new, old, adv, mask, eps)
    # rollout 0 (A=2): min(1.05*2, 1.05*2) = 2.1; min(1.5*2, 1.1*2) = 2.2
    # rollout 1 (A=-1): min(-0.5, -0.9) = -0.9; -1; -1
    expected = -(2.1 + 2.2 - 0.9 - 1.0 - 1.0) / 5
    assert math.isclose(loss.item(), expected, rel_tol=1e-6)
    assert math.isclose(stats["clip_fraction"], 2 / 5, rel_tol=1e-6)  # 1.5 and 0.5 are outside [0.9, 1.1]; 9.0 is padding
    ratios = torch.tensor([1.05, 1.5, 0.5, 1.0, 1.0])
    assert math.isclose(stats["approx_kl"], float(((ratios - 1) - ratios.log()).sum() / 5), rel_tol=1e-6)


def test_ppo_gradient_vanishes_once_the_ratio_is_clipped_in_the_advantage_direction():
    new = torch.log(torch.tensor([[1.2, 0.95]])).requires_grad_()
    loss, _ = ppo_loss(new, torch.zeros(1, 2), torch.tensor([1.0]), torch.ones(1, 2), 0.1)
    loss.backward()
    assert new.grad[0, 0] == 0 and new.grad[0, 1] < 0  # clipped above 1.1: no push; inside: push up


@pytest.mark.parametrize("eps", [0.0, -0.1])
def test_non_positive_epsilon_is_rejected(eps):
    with pytest.raises(ValueError, match="epsilon must be > 0"):
        ppo_loss(torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1), torch.ones(1, 1), eps)
