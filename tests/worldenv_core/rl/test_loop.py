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


class ActionRewardEnv:
    """A stand-in for the imagined env whose reward is known: the share of x-actions > 0 in a
    rollout's chunks (observations stay put). Each rollout lasts two chunks."""

    chunk = 4

    def reset(self, contexts):
        from worldenv_core.imagination.env import StepResult

        b = len(contexts)
        self.frames = torch.stack([c.frame for c in contexts])
        self.state = StepResult(frames=self.frames, proprio=torch.zeros(b, 7), reward=torch.zeros(b),
                                done=torch.zeros(b, dtype=torch.bool), t=torch.zeros(b, dtype=torch.long),
                                by_reflector=torch.zeros(b, dtype=torch.bool))
        self.positive = []
        return self.state

    def step(self, actions, generator=None):
        from worldenv_core.imagination.env import StepResult

        self.positive.append((actions[..., 0] > 0).float().mean(1))
        t = self.state.t + self.chunk
        self.state = StepResult(frames=self.frames, proprio=self.state.proprio, reward=torch.stack(self.positive).mean(0),
                                done=t >= 2 * self.chunk, t=t, by_reflector=torch.zeros_like(self.state.done))
        return self.state


def _policy_and_contexts(n_contexts: int = 2):
    from hydra.utils import instantiate

    from worldenv_core.imagination.env import Context

    torch.manual_seed(0)
    policy = instantiate({"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": ["agentview"], "chunk": 4,
                          "hidden": 32, "instruction_dim": 8,
                          "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone",
                                       "cameras": ["agentview"], "cond_dim": 8, "widths": [8, 8], "keypoints": 4}})
    g = torch.Generator().manual_seed(0)
    contexts = [Context(task_id=0, instruction=f"task {i}", frame=torch.randint(0, 255, (3, 16, 16), generator=g,
                                                                                   dtype=torch.uint8),
                        proprio=torch.zeros(7)) for i in range(n_contexts)]
    return policy, contexts, lambda texts: torch.ones(len(texts), 8)


def test_a_tiny_loop_improves_a_synthetic_reward():
    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    opt = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-2))
    env, rewards = ActionRewardEnv(), []
    for it in range(12):
        batch = collect_rollouts(policy, env, contexts, 8, encoder, torch.Generator().manual_seed(it))
        assert batch.actions.shape == (16, 2, 4, 7) and batch.mask.all()
        assert torch.allclose(batch.advantages.view(2, 8).sum(1), torch.zeros(2), atol=1e-5)
        rewards.append(batch.rewards.mean().item())
        ppo_update(policy, opt, batch, epochs=2, epsilon=0.1, minibatch=8, generator=torch.Generator().manual_seed(it))
    assert sum(rewards[-3:]) / 3 > sum(rewards[:3]) / 3 + 0.15, rewards


def test_target_kl_stops_an_iterations_ppo_steps_once_the_policy_has_moved_that_far():
    """Without a target every epoch x minibatch step is taken; with one, the steps stop at the
    first minibatch whose KL from the behaviour policy exceeds 1.5 x target (the first minibatch
    is always taken: the policy has not moved yet), and the policy moves less."""
    import copy

    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    batch = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0))
    moved, steps = {}, {}
    for target in (None, 1e-4):
        p = copy.deepcopy(policy)
        steps[target] = ppo_update(p, torch.optim.Adam(policy_param_groups(p, 1e-2, 1e-1)), batch, epochs=3,
                                   epsilon=0.1, minibatch=4, generator=torch.Generator().manual_seed(0),
                                   target_kl=target)["ppo_steps"]
        moved[target] = sum(float((a - b).norm()) for a, b in zip(p.parameters(), policy.parameters()))
    assert steps[None] == 12 and 1 <= steps[1e-4] < 12, steps  # 16 rollouts / 4 a minibatch x 3 epochs
    assert moved[1e-4] < moved[None], moved


def test_rollouts_drawn_per_context_are_the_same_however_the_contexts_are_split():
    """What sharding imagined rollouts over ranks relies on: a context's N rollouts depend on its
    own generator, not on which contexts share its batch; the parts merge back into the batch."""
    from worldenv_core.rl.loop import collect_rollouts, merge

    policy, contexts, encoder = _policy_and_contexts(3)
    streams = lambda: [torch.Generator().manual_seed(s) for s in (11, 12, 13)]  # noqa: E731
    whole = collect_rollouts(policy, ActionRewardEnv(), contexts, 4, encoder, streams())
    g = streams()
    parts = [collect_rollouts(policy, ActionRewardEnv(), contexts[:1], 4, encoder, g[:1]),
             collect_rollouts(policy, ActionRewardEnv(), contexts[1:], 4, encoder, g[1:])]
    merged = merge(parts)
    for name in ("actions", "logp_old", "mask", "rewards", "advantages", "frames", "instruction"):
        torch.testing.assert_close(getattr(merged, name), getattr(whole, name), msg=name)
    one_generator = collect_rollouts(policy, ActionRewardEnv(), contexts, 4, encoder, torch.Generator().manual_seed(11))
    assert not torch.allclose(one_generator.actions[4:], whole.actions[4:])  # the split-free draw is another one
    short = parts[0]  # a part whose rollouts all ended a chunk sooner: padded, and the padding masked
    short.frames, short.proprio, short.actions = short.frames[:, :1], short.proprio[:, :1], short.actions[:, :1]
    short.logp_old, short.mask = short.logp_old[:, :1], short.mask[:, :1]
    padded = merge([short, parts[1]])
    assert padded.actions.shape == whole.actions.shape and (padded.mask[:4, 1] == 0).all()
    assert (padded.mask[4:] == whole.mask[4:]).all()


def test_groups_whose_verdicts_all_agree_are_dropped_before_ppo():
    from worldenv_core.rl.loop import RolloutBatch, informative_groups, select

    # 3 contexts x 2 rollouts: both succeed, one of two succeeds, both fail (scores just below eta)
    success = torch.tensor([True, True, True, False, False, False])
    rewards = torch.tensor([0.9, 0.8, 0.7, 0.2, 0.3, 0.1])
    r = len(rewards)
    batch = RolloutBatch(frames=torch.zeros(r, 2, 3, 4, 4, dtype=torch.uint8), proprio=torch.zeros(r, 2, 7),
                         instruction=torch.arange(r).float()[:, None], actions=torch.zeros(r, 2, 4, 7),
                         logp_old=torch.zeros(r, 2, 4), mask=torch.ones(r, 2, 4), rewards=rewards,
                         advantages=rloo_advantages(rewards.view(3, 2)).reshape(-1), t_end=torch.full((r,), 8),
                         by_reflector=success, beta_mean=0.0)
    keep = informative_groups(batch, 2)
    assert keep.tolist() == [False, False, True, True, False, False]
    kept = select(batch, keep)
    assert kept.instruction[:, 0].tolist() == [2.0, 3.0] and torch.allclose(kept.advantages, torch.tensor([0.5, -0.5]))
    assert kept.frames.shape[0] == kept.mask.shape[0] == 2


def test_permuted_verdicts_keep_how_many_succeed_and_move_them_to_other_rollouts():
    from worldenv_core.rl.loop import RolloutBatch, permute_verdicts

    rewards = torch.tensor([0.9, 0.1, 0.2, 0.1, 0.8, 0.7, 0.1, 0.3])
    r = len(rewards)
    batch = RolloutBatch(frames=torch.zeros(r, 1, 3, 4, 4, dtype=torch.uint8), proprio=torch.zeros(r, 1, 7),
                         instruction=torch.arange(r).float()[:, None], actions=torch.zeros(r, 1, 4, 7),
                         logp_old=torch.zeros(r, 1, 4), mask=torch.ones(r, 1, 4), rewards=rewards,
                         advantages=rloo_advantages(rewards.view(2, 4)).reshape(-1), t_end=torch.arange(r),
                         by_reflector=rewards > 0.5, beta_mean=0.0)
    out = permute_verdicts(batch, 4, torch.Generator().manual_seed(0))
    assert sorted(out.rewards.tolist()) == sorted(rewards.tolist()) and not torch.equal(out.rewards, rewards)
    assert torch.equal(out.by_reflector, out.rewards > 0.5)  # each verdict moves with its reward
    assert torch.allclose(out.advantages, rloo_advantages(out.rewards.view(2, 4)).reshape(-1))
    assert torch.equal(out.t_end, batch.t_end) and torch.equal(out.instruction, batch.instruction)  # rollouts stay


def _batch_of_verdicts(success: list[bool], n: int):
    from worldenv_core.rl.loop import RolloutBatch

    s = torch.tensor(success)
    r, rewards = len(s), s.float()
    return RolloutBatch(frames=torch.zeros(r, 1, 3, 4, 4, dtype=torch.uint8), proprio=torch.zeros(r, 1, 7),
                        instruction=torch.arange(r).float()[:, None], actions=torch.zeros(r, 1, 4, 7),
                        logp_old=torch.zeros(r, 1, 4), mask=torch.ones(r, 1, 4), rewards=rewards,
                        advantages=rloo_advantages(rewards.view(-1, n)).reshape(-1), t_end=torch.full((r,), 4),
                        by_reflector=s, beta_mean=0.0)


def test_groups_are_filtered_by_their_success_fraction():
    """With a [lo, hi] range a mixed group also needs its success fraction inside it (10-90 % as
    SimpleVLA-RL and WoVR): of four groups of 10 with 0, 1, 5 and 9 successes, [0.1, 0.9] keeps
    the mixed three, [0.2, 0.8] only the one with 5; the bounds are checked."""
    from worldenv_core.rl.loop import check_success_range, informative_groups

    groups = [[True] * k + [False] * (10 - k) for k in (0, 1, 5, 9)]
    batch = _batch_of_verdicts([v for g in groups for v in g], 10)
    kept = lambda rng: informative_groups(batch, 10, rng).view(4, 10)[:, 0].tolist()  # noqa: E731
    assert kept(None) == [False, True, True, True]
    assert kept((0.1, 0.9)) == [False, True, True, True]
    assert kept((0.2, 0.8)) == [False, False, True, False]
    assert kept((0.0, 1.0)) == kept(None)  # all-agreeing groups carry no advantage: dropped at any range
    assert check_success_range(None) is None and check_success_range([0.1, 0.9]) == (0.1, 0.9)
    for bad in ([0.9, 0.1], [-0.1, 0.5], [0.5, 1.5]):
        with pytest.raises(ValueError, match="two fractions"):
            check_success_range(bad)


def test_the_trust_region_bounds_the_exact_kl_of_every_update_the_first_step_included():
    """At a learning rate whose first Adam step alone moves the policy far (as measured on the
    project's policy), `max_kl` measures the exact Laplace KL after every step, shrinks the step
    that crosses it and stops: the update ends within the bound, where the same update without
    it ends far beyond; and it is refused without the behaviour's Laplace parameters."""
    import copy
    import dataclasses

    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    batch = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0))
    assert batch.mu_old.shape == batch.actions.shape == batch.beta_old.shape
    out = {}
    for bound in (None, 0.01):
        p = copy.deepcopy(policy)
        out[bound] = ppo_update(p, torch.optim.Adam(policy_param_groups(p, 1e-3, 1e-3)), batch, epochs=3, epsilon=0.2,
                                minibatch=4, generator=torch.Generator().manual_seed(0), max_kl=bound,
                                direction_groups=8)
    free, bounded = out[None], out[0.01]
    # the two contexts' policy gradients before any step: the same for both runs, a cosine
    assert free["direction_cosine"] == pytest.approx(bounded["direction_cosine"]) and -1 <= free["direction_cosine"] <= 1
    assert free["exact_kl"] > 0.1 and free["ppo_steps"] == 12, free
    assert bounded["exact_kl"] <= 0.01 + 1e-6 and bounded["trust_region_hit"] == 1.0, bounded
    assert bounded["first_step_kl"] > 0 and bounded["ppo_steps"] < 12 and bounded["backtracks"] >= 1
    assert 0 < bounded["action_shift_rms"] < free["action_shift_rms"]
    with pytest.raises(ValueError, match="needs the behaviour's Laplace"):
        ppo_update(policy, torch.optim.Adam(policy.parameters()), dataclasses.replace(batch, mu_old=None), 1, 0.2, 4,
                   max_kl=0.01)
    with pytest.raises(ValueError, match="max_kl must be > 0"):
        ppo_update(policy, torch.optim.Adam(policy.parameters()), batch, 1, 0.2, 4, max_kl=0.0)


def test_the_trust_regions_kl_is_of_the_distributions_the_actions_were_drawn_from():
    """Drawn at a temperature (`noise_scale` k), the same move of the mean is a smaller KL between
    the sampling distributions (scale k e^beta): about 1/k^2 of it for a small move."""
    import dataclasses

    from worldenv_core.rl.loop import kl_probe, collect_rollouts

    policy, contexts, encoder = _policy_and_contexts()
    batch = collect_rollouts(policy, ActionRewardEnv(), contexts, 4, encoder, torch.Generator().manual_seed(0))
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    kls = {k: kl_probe(dataclasses.replace(batch, noise_scale=k), 512, None).summary(policy) for k in (1.0, 2.0)}
    assert kls[1.0]["action_shift_rms"] == kls[2.0]["action_shift_rms"] > 0
    assert 0.15 < kls[2.0]["exact_kl"] / kls[1.0]["exact_kl"] < 0.6


def test_which_parameters_rl_trains_and_with_which_optimiser():
    """A learning rate of 0 leaves its group out; scale_head=False keeps the Laplace scale as SFT
    fitted it; sgd and adam are the optimisers, any other name refused."""
    from worldenv_core.rl.loop import make_optimizer, policy_param_groups

    policy, _, _ = _policy_and_contexts()
    ids = lambda groups: {id(p) for g in groups for p in g["params"]}  # noqa: E731
    backbone, scale = {id(p) for p in policy.backbone.parameters()}, {id(p) for p in policy.scale_head.parameters()}
    every = ids(policy_param_groups(policy, 1e-4, 1e-5))
    assert backbone | scale <= every
    heads_only = ids(policy_param_groups(policy, 0.0, 1e-5))
    assert not heads_only & backbone and scale <= heads_only
    assert not ids(policy_param_groups(policy, 1e-4, 1e-5, scale_head=False)) & scale
    with pytest.raises(ValueError, match="one of them > 0"):
        policy_param_groups(policy, 0.0, 0.0)
    assert isinstance(make_optimizer(policy, "sgd", 1e-4, 1e-5), torch.optim.SGD)
    assert isinstance(make_optimizer(policy, "adam", 1e-4, 1e-5), torch.optim.Adam)
    with pytest.raises(ValueError, match="rl.optimizer must be one of"):
        make_optimizer(policy, "rmsprop", 1e-4, 1e-5)


def test_rollouts_drawn_at_a_sampling_temperature_carry_its_log_probs_and_ppo_starts_at_ratio_one():
    """noise_scale s: actions ~ Laplace(mu, s e^beta); the behaviour log-probs are of that
    distribution and PPO's new ones too, so the first minibatch's ratios are exactly 1."""
    import math

    from worldenv_core.models.laplace import laplace_log_prob
    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    calm = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0))
    hot = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0), noise_scale=2.0)
    assert hot.noise_scale == 2.0 and torch.allclose(hot.mu_old, calm.mu_old)
    spread = lambda b: float((b.actions - b.mu_old).abs().mean())  # noqa: E731
    assert spread(hot) == pytest.approx(2 * spread(calm), rel=1e-4)  # the same draws, twice as far
    torch.testing.assert_close(hot.logp_old, laplace_log_prob(hot.actions, hot.mu_old, hot.beta_old + math.log(2.0)))
    out = ppo_update(policy, torch.optim.Adam(policy_param_groups(policy, 1e-4, 1e-4)), hot, epochs=1, epsilon=0.2,
                     minibatch=16, generator=torch.Generator().manual_seed(0))
    assert out["approx_kl"] == pytest.approx(0.0, abs=1e-6) and out["ratio_mean"] == pytest.approx(1.0, abs=1e-5)


def test_ppo_runs_the_policy_as_the_behaviour_ran_so_dropout_cannot_break_the_ratio():
    """A policy with dropout (LeRobot's ACT has 0.1) is trained in eval mode: an unchanged policy's
    ratio is exactly 1, where a dropout mask on mu would put it near 0."""
    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    policy.register_forward_hook(lambda m, args, out: (torch.nn.functional.dropout(out[0], 0.5, m.training), out[1]))
    batch = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0))
    out = ppo_update(policy, torch.optim.SGD(policy.parameters(), lr=0.0), batch, epochs=1,
                     epsilon=0.2, minibatch=16, generator=torch.Generator().manual_seed(0))
    assert out["ratio_mean"] == pytest.approx(1.0, abs=1e-5) and not policy.training


def test_the_gradients_signal_and_noise_are_recovered_from_its_groups():
    """Groups' gradients s + noise: the estimate recovers |s|^2 and sigma^2, and the number of
    groups at which the batch's direction is the reward's to cos 0.9; pure noise has no signal."""
    from worldenv_core.rl.loop import gradient_signal

    g = torch.Generator().manual_seed(0)
    dim, groups = 20_000, 64
    s = torch.zeros(dim)
    s[:100] = 10.0  # |s|^2 = 1e4
    grads = s + 5.0 * torch.randn(groups, dim, generator=g)  # sigma^2 = 25 x 20000 = 5e5 per group
    out = gradient_signal(grads.sum(0), float(grads.pow(2).sum()), groups)
    assert out["gradient_signal_sq"] == pytest.approx(1e4, rel=0.2)
    assert out["gradient_noise_sq"] == pytest.approx(5e5, rel=0.02)
    assert out["groups_for_cos_0.9"] == pytest.approx(0.81 / 0.19 * 5e5 / 1e4, rel=0.2)  # ~210 groups
    noise = 5.0 * torch.randn(groups, dim, generator=g)
    none = gradient_signal(noise.sum(0), float(noise.pow(2).sum()), groups)
    assert abs(none["gradient_signal_sq"]) < 0.2 * 5e5 / groups and none["groups_for_cos_0.9"] > 1000
    with pytest.raises(ValueError, match="at least 2 groups"):
        gradient_signal(grads[0], 1.0, 1)


def test_rollouts_with_a_chunk_held_draw_carry_its_log_probs_and_a_tiny_loop_learns_with_them():
    """exploration=chunk: each chunk's actions are its means plus one held offset, the batch's
    log-probs are of that draw (PPO starts at ratio exactly 1) and LOOP improves the reward with them."""
    from worldenv_core.models.laplace import chunk_log_prob
    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update

    policy, contexts, encoder = _policy_and_contexts()
    batch = collect_rollouts(policy, ActionRewardEnv(), contexts, 8, encoder, torch.Generator().manual_seed(0),
                             exploration="chunk")
    assert batch.exploration == "chunk"
    eta = (batch.actions - batch.mu_old) / batch.beta_old.exp()
    assert float((eta - eta[:, :, :1]).abs().max()) < 1e-4
    torch.testing.assert_close(batch.logp_old, chunk_log_prob(batch.actions, batch.mu_old, batch.beta_old, 1.0, "chunk"))
    out = ppo_update(policy, torch.optim.Adam(policy_param_groups(policy, 1e-4, 1e-4)), batch, epochs=1, epsilon=0.2,
                     minibatch=16, generator=torch.Generator().manual_seed(0))
    assert out["approx_kl"] == pytest.approx(0.0, abs=1e-6) and out["ratio_mean"] == pytest.approx(1.0, abs=1e-5)

    policy, contexts, encoder = _policy_and_contexts()
    opt = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-2))
    env, rewards = ActionRewardEnv(), []
    for it in range(12):
        batch = collect_rollouts(policy, env, contexts, 8, encoder, torch.Generator().manual_seed(it), exploration="chunk")
        rewards.append(batch.rewards.mean().item())
        ppo_update(policy, opt, batch, epochs=2, epsilon=0.1, minibatch=8, generator=torch.Generator().manual_seed(it))
    assert sum(rewards[-3:]) / 3 > sum(rewards[:3]) / 3 + 0.15, rewards
