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


EXPLORATION = ("step", "chunk")


def check_exploration(exploration: str) -> None:
    if exploration not in EXPLORATION:
        raise ValueError(f"exploration must be one of {EXPLORATION}, got {exploration!r}")


def laplace_sample(mu: torch.Tensor, beta: torch.Tensor, generator: torch.Generator | None = None,
                   scale: float = 1.0, exploration: str = "step") -> torch.Tensor:
    """Draw a ~ Laplace(mu, scale * exp(beta)) by inverting the CDF of a uniform draw. `generator`
    may be a list, one per equal block of rows (`distributed.random_rows`). `exploration`: step, a
    draw per element (the paper); chunk, one standard draw eta per action dimension of a chunk
    (mu: (..., K, A)), a_k = mu_k + scale e^beta_k eta at each of its K steps (`chunk_log_prob`)."""
    check_exploration(exploration)
    shape = (*mu.shape[:-2], 1, mu.shape[-1]) if exploration == "chunk" else mu.shape
    u = random_rows(torch.rand, shape, generator, device=mu.device, dtype=mu.dtype) - 0.5
    u = u.clamp(-0.5 + 1e-7, 0.5 - 1e-7)  # keep log1p finite at the tails
    b = scale * torch.exp(beta)
    return mu - b * torch.sign(u) * torch.log1p(-2.0 * u.abs())


def laplace_kl(mu_p: torch.Tensor, beta_p: torch.Tensor, mu_q: torch.Tensor, beta_q: torch.Tensor) -> torch.Tensor:
    """Per-element KL(Laplace(mu_p, e^beta_p) || Laplace(mu_q, e^beta_q)), in closed form:
    beta_q - beta_p + |mu_p - mu_q| / b_q + (b_p / b_q) exp(-|mu_p - mu_q| / b_p) - 1."""
    d = (mu_p - mu_q).abs()
    return beta_q - beta_p + d * torch.exp(-beta_q) + torch.exp(beta_p - beta_q - d * torch.exp(-beta_p)) - 1.0


def chunk_log_prob(actions: torch.Tensor, mu: torch.Tensor, beta: torch.Tensor, scale: float = 1.0,
                   exploration: str = "step") -> torch.Tensor:
    """The log-probability of chunks (..., K, A) as `laplace_sample` drew them, per executed step (..., K).

    step: log Laplace(a_k; mu_k, scale e^beta_k) summed over action dimensions. chunk: the chunk's one
    draw eta read back from its steps, eta = mean_k (a_k - mu_k) / b_k with b_k = scale e^beta_k, and
    log p = sum_A (-|eta| - log 2) - mean_k sum_A log b_k, the same at each of its K steps (so a
    per-step PPO ratio is the chunk's). Under the behaviour eta is exact; under a moved policy it is
    the draw that the moved means' average over the chunk implies: the score pushes the chunk's mean
    along the offset that was tried (a random offset held for K steps moves the arm sqrt(K) times
    as far as K independent ones of its size, with K times fewer draws to credit)."""
    check_exploration(exploration)
    if exploration == "step":
        return laplace_log_prob(actions, mu, beta + math.log(scale))
    log_b = beta + math.log(scale)
    eta = ((actions - mu) * torch.exp(-log_b)).mean(-2)
    lp = -(eta.abs() + LOG2).sum(-1) - log_b.mean(-2).sum(-1)
    return lp[..., None].expand(actions.shape[:-1])
