"""The critic's per-chunk advantages: GAE by hand, PPO's loss with credit per chunk, a critic that
learns what its features say, and the stage's ChunkValue (RLOO until its first fit, then GAE from
a critic that never saw the batch it judges; its state round-trips) learning a tiny reward."""
import dataclasses

import pytest
import torch

from tests.worldenv_core.rl.test_loop import ActionRewardEnv, _policy_and_contexts
from worldenv_core.rl.critic import ChunkCritic, ChunkValue, critic_bce, fit_critic, gae_advantages
from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_loss, ppo_update


def test_gae_by_hand_with_the_reward_at_each_rollouts_last_live_chunk():
    values = torch.tensor([[0.5, 0.6, 0.8], [0.4, 0.2, 0.9]])
    live = torch.tensor([[1, 1, 1], [1, 1, 0]])  # rollout 1 ended after two chunks (its third value is padding)
    rewards = torch.tensor([1.0, 0.0])
    lam1 = gae_advantages(values, live, rewards, 1.0)  # R - V(s_t)
    assert torch.allclose(lam1, torch.tensor([[0.5, 0.4, 0.2], [-0.4, -0.2, 0.0]]))
    lam0 = gae_advantages(values, live, rewards, 0.0)  # one-step TD errors, the reward at the end
    assert torch.allclose(lam0, torch.tensor([[0.1, 0.2, 0.2], [-0.2, -0.2, 0.0]]))
    half = gae_advantages(values, live, rewards, 0.5)
    assert torch.allclose(half, torch.tensor([[0.25, 0.3, 0.2], [-0.3, -0.2, 0.0]]))
    with pytest.raises(ValueError, match="lambda must be in"):
        gae_advantages(values, live, rewards, 1.5)


def test_ppo_loss_takes_one_advantage_per_chunk_and_a_chunk_without_credit_gets_no_gradient():
    g = torch.Generator().manual_seed(0)
    logp_old = torch.randn(3, 2 * 4, generator=g)
    logp_new = (logp_old + 0.05 * torch.randn(3, 8, generator=g)).requires_grad_()
    mask = torch.ones(3, 8)
    adv = torch.tensor([0.5, -1.0, 0.2])
    per_rollout, _ = ppo_loss(logp_new, logp_old, adv, mask, 0.2)
    per_chunk, _ = ppo_loss(logp_new, logp_old, adv[:, None].expand(3, 2), mask, 0.2)
    assert torch.allclose(per_rollout, per_chunk)
    credit = torch.tensor([[1.0, 0.0], [0.0, -1.0], [0.3, 0.0]])
    loss, _ = ppo_loss(logp_new, logp_old, credit, mask, 0.2)
    (grad,) = torch.autograd.grad(loss, logp_new)
    assert torch.all(grad.view(3, 2, 4)[credit == 0] == 0) and torch.all(grad.view(3, 2, 4)[credit != 0] != 0)
    with pytest.raises(ValueError, match="do not divide"):
        ppo_loss(logp_new, logp_old, torch.zeros(3, 3), mask, 0.2)


def test_a_critic_learns_what_its_features_say_about_success():
    g = torch.Generator().manual_seed(0)
    feats, chunk = torch.randn(2000, 8, generator=g), torch.randint(10, (2000,), generator=g)
    success = ((feats[:, 0] + 0.1 * chunk) > 0.5).float()  # the state and the depth both matter
    critic = ChunkCritic(8, horizon_chunks=10, hidden=32)
    stats = fit_critic(critic, torch.optim.Adam(critic.parameters(), 1e-2), feats[:1500], chunk[:1500], success[:1500],
                       steps=300, minibatch=128, generator=g)
    held_out = critic_bce(critic, feats[1500:], chunk[1500:], success[1500:])
    constant = float(torch.nn.functional.binary_cross_entropy(torch.full((500,), float(success.mean())), success[1500:]))
    assert stats["critic_loss_last"] < stats["critic_loss_first"] and held_out < 0.5 * constant


def test_chunk_value_keeps_rloo_until_it_has_learned_then_gives_credit_per_chunk_and_resumes_bit_identical():
    policy, contexts, encoder = _policy_and_contexts()
    value = ChunkValue(horizon_chunks=2, hidden=16, lr=1e-2, steps=50, minibatch=8, lam=0.9, replay=1)
    first = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0))
    adv, stats = value.advantages(policy, first, torch.Generator().manual_seed(0))
    assert adv is first.advantages and stats["critic_fits"] == 0 and value.fits == 1  # no critic yet: RLOO's
    second = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(1))
    saved = value.state_dict()
    twin = ChunkValue(horizon_chunks=2, hidden=16, lr=1e-2, steps=50, minibatch=8, lam=0.9, replay=1)
    twin.load_state_dict(saved)
    adv, stats = value.advantages(policy, second, torch.Generator().manual_seed(1))
    again, _ = twin.advantages(policy, second, torch.Generator().manual_seed(1))  # a resumed run does the same
    assert adv.shape == (16, 2) and torch.equal(adv, again)
    assert {"critic_bce", "critic_bce_constant", "advantage_abs_mean"} <= set(stats) and value.fits == 2
    assert stats["critic_fit_chunks"] == 2 * 32  # this batch's 16 x 2 chunks and the one before it (replay=1)
    third = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(2))
    assert value.advantages(policy, third)[1]["critic_fit_chunks"] == 2 * 32 and len(value.kept) == 2  # the oldest left
    out = ppo_update(policy, torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-2)),
                     dataclasses.replace(second, advantages=adv), epochs=1, epsilon=0.1, minibatch=8)
    assert out["ppo_steps"] == 2 and torch.isfinite(torch.tensor(out["loss"]))
    with pytest.raises(ValueError, match="gae_lambda"):
        ChunkValue(2, 16, 1e-2, 50, 8, lam=-0.1)
    with pytest.raises(ValueError, match="critic_replay"):
        ChunkValue(2, 16, 1e-2, 50, 8, lam=0.9, replay=-1)


def test_a_tiny_loop_with_the_critics_advantages_improves_a_synthetic_reward():
    policy, contexts, encoder = _policy_and_contexts()
    opt = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-2))
    value = ChunkValue(horizon_chunks=2, hidden=16, lr=1e-2, steps=50, minibatch=16, lam=0.95)
    env, rewards = ActionRewardEnv(), []
    for it in range(12):
        batch = collect_rollouts(policy, env, contexts, 8, encoder, torch.Generator().manual_seed(it))
        rewards.append(batch.rewards.mean().item())
        adv, _ = value.advantages(policy, batch, torch.Generator().manual_seed(it))
        ppo_update(policy, opt, dataclasses.replace(batch, advantages=adv), epochs=2, epsilon=0.1, minibatch=8,
                   generator=torch.Generator().manual_seed(it))
    assert sum(rewards[-3:]) / 3 > sum(rewards[:3]) / 3 + 0.15, rewards
