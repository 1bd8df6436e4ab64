"""LOOP (paper sec. 4.3, Algorithm 1): RLOO advantages and the clipped PPO objective of eq. 5.

Shapes: a batch holds C contexts x N rollouts. Per-step log-probabilities are over one executed
action (the sum over its action dimensions); `mask` marks the steps a rollout really took
(1..T_n), so padding after termination never counts.
"""

from __future__ import annotations

import torch


def rloo_advantages(rewards: torch.Tensor) -> torch.Tensor:
    """rewards (C, N) -> A_n = R_n - mean of the other N - 1 rewards of the same context."""
    n = rewards.shape[-1]
    if n < 2:
        raise ValueError(f"RLOO needs at least 2 rollouts per context, got N={n}")
    baseline = (rewards.sum(-1, keepdim=True) - rewards) / (n - 1)
    return rewards - baseline


def ppo_loss(logp_new: torch.Tensor, logp_old: torch.Tensor, advantages: torch.Tensor, mask: torch.Tensor,
             epsilon: float) -> tuple[torch.Tensor, dict]:
    """Eq. 5: -(1 / sum_n T_n) sum_n sum_t min(r A_n, clip(r, 1 - eps, 1 + eps) A_n).

    logp_new, logp_old, mask: (R, T) over R rollouts; advantages (R,), broadcast over each
    trajectory. Returns the loss and diagnostics (clip fraction, approximate KL, mean ratio)."""
    if not epsilon > 0:
        raise ValueError(f"PPO clip epsilon must be > 0, got {epsilon}")
    mask = mask.float()
    steps = mask.sum().clamp(min=1.0)
    log_ratio = (logp_new - logp_old) * mask
    ratio = log_ratio.exp()
    adv = advantages[:, None].expand_as(ratio)
    surrogate = torch.minimum(ratio * adv, ratio.clamp(1 - epsilon, 1 + epsilon) * adv)
    loss = -(surrogate * mask).sum() / steps
    with torch.no_grad():
        clipped = ((ratio - 1).abs() > epsilon).float()
        stats = {"clip_fraction": float((clipped * mask).sum() / steps),
                 # the low-variance estimator (r - 1) - log r of KL(old || new)
                 "approx_kl": float((((ratio - 1) - log_ratio) * mask).sum() / steps),
                 "ratio_mean": float((ratio * mask).sum() / steps)}
    return loss, stats
