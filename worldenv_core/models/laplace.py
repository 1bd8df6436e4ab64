"""The factorised Laplace action distribution of the paper (eq. 6-8, Algorithm 1 line 12).

mu is the action head's output, beta = log b the scale head's; a ~ Laplace(mu, exp(beta)) per
dimension, independently. Written out rather than through torch.distributions so the same
expressions serve the SFT loss, sampling and the PPO importance ratios without re-validation.
"""

from __future__ import annotations

import math

import torch

from worldenv_core.distributed import random_rows

LOG2 = math.log(2.0)


def laplace_nll(action: torch.Tensor, mu: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Per-element negative log-likelihood |a - mu| * exp(-beta) + beta + log 2 (paper eq. 8)."""
    return (action - mu).abs() * torch.exp(-beta) + beta + LOG2


def laplace_log_prob(action: torch.Tensor, mu: torch.Tensor, beta: torch.Tensor, event_dims: int = 1) -> torch.Tensor:
    """log p(a) summed over the last `event_dims` dimensions (action dims; 2 for a whole chunk)."""
    lp = -laplace_nll(action, mu, beta)
    return lp.sum(dim=tuple(range(-event_dims, 0))) if event_dims else lp


def laplace_sample(mu: torch.Tensor, beta: torch.Tensor, generator: torch.Generator | None = None,
                   scale: float = 1.0) -> torch.Tensor:
    """Draw a ~ Laplace(mu, scale * exp(beta)) by inverting the CDF of a uniform draw. `generator`
    may be a list, one per equal block of rows (`distributed.random_rows`)."""
    u = random_rows(torch.rand, mu.shape, generator, device=mu.device, dtype=mu.dtype) - 0.5
    u = u.clamp(-0.5 + 1e-7, 0.5 - 1e-7)  # keep log1p finite at the tails
    b = scale * torch.exp(beta)
    return mu - b * torch.sign(u) * torch.log1p(-2.0 * u.abs())


def laplace_kl(mu_p: torch.Tensor, beta_p: torch.Tensor, mu_q: torch.Tensor, beta_q: torch.Tensor) -> torch.Tensor:
    """Per-element KL(Laplace(mu_p, e^beta_p) || Laplace(mu_q, e^beta_q)), in closed form:
    beta_q - beta_p + |mu_p - mu_q| / b_q + (b_p / b_q) exp(-|mu_p - mu_q| / b_p) - 1."""
    d = (mu_p - mu_q).abs()
    return beta_q - beta_p + d * torch.exp(-beta_q) + torch.exp(beta_p - beta_q - d * torch.exp(-beta_p)) - 1.0
