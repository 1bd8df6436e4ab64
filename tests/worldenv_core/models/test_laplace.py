import math

import torch

from worldenv_core.models.laplace import laplace_log_prob, laplace_nll, laplace_sample


def test_nll_and_log_prob_match_torch():
    g = torch.Generator().manual_seed(0)
    mu, beta = torch.randn(4, 8, 7, generator=g), torch.randn(4, 8, 7, generator=g)
    a = torch.randn(4, 8, 7, generator=g)
    ref = torch.distributions.Laplace(mu, beta.exp())
    assert torch.allclose(laplace_nll(a, mu, beta), -ref.log_prob(a), atol=1e-6)
    assert torch.allclose(laplace_log_prob(a, mu, beta), ref.log_prob(a).sum(-1), atol=1e-5)
    assert torch.allclose(laplace_log_prob(a, mu, beta, event_dims=2), ref.log_prob(a).sum((-1, -2)), atol=1e-4)


def test_nll_is_the_papers_formula_at_a_point():
    nll = laplace_nll(torch.tensor(1.0), torch.tensor(0.5), torch.tensor(math.log(0.25)))
    assert math.isclose(nll.item(), 0.5 / 0.25 + math.log(0.25) + math.log(2), rel_tol=1e-6)


def test_samples_have_the_laplace_moments():
    mu, beta = torch.full((200_000,), 0.3), torch.full((200_000,), math.log(0.2))
    a = laplace_sample(mu, beta, torch.Generator().manual_seed(1))
    assert abs(a.median().item() - 0.3) < 0.01
    assert abs((a - 0.3).abs().mean().item() - 0.2) < 0.005  # E|a - mu| = b
    a2 = laplace_sample(mu, beta, torch.Generator().manual_seed(1), scale=2.0)
    assert abs((a2 - 0.3).abs().mean().item() - 0.4) < 0.01


def test_kl_in_closed_form_matches_a_monte_carlo_estimate_and_vanishes_only_at_equality():
    from worldenv_core.models.laplace import laplace_kl

    mu_p, beta_p = torch.tensor([0.1, -0.3, 0.0]), torch.tensor([-2.5, -1.0, 0.2])
    mu_q, beta_q = torch.tensor([0.15, 0.2, 0.0]), torch.tensor([-2.3, -1.0, -0.4])
    p = torch.distributions.Laplace(mu_p, beta_p.exp())
    x = laplace_sample(mu_p.expand(400_000, 3), beta_p.expand(400_000, 3), torch.Generator().manual_seed(0))
    mc = (p.log_prob(x) - torch.distributions.Laplace(mu_q, beta_q.exp()).log_prob(x)).mean(0)
    exact = laplace_kl(mu_p, beta_p, mu_q, beta_q)
    assert torch.allclose(exact, mc, rtol=0.03, atol=2e-3), (exact, mc)
    assert torch.allclose(exact, torch.distributions.kl_divergence(p, torch.distributions.Laplace(mu_q, beta_q.exp())),
                          atol=1e-5)
    assert torch.allclose(laplace_kl(mu_p, beta_p, mu_p, beta_p), torch.zeros(3), atol=1e-7)
    assert (exact > 0).all()


def test_a_chunk_held_draw_is_one_laplace_offset_per_dimension_in_units_of_each_steps_scale():
    """exploration=chunk: a_k = mu_k + s e^beta_k eta with one standard Laplace eta per chunk and
    action dimension; its log-probability is eta's density (less the scales' mean log), the same at
    every step, and it only accepts the two modes."""
    import pytest

    from worldenv_core.models.laplace import chunk_log_prob

    g = torch.Generator().manual_seed(0)
    mu, beta = torch.randn(20_000, 8, 7, generator=g), torch.randn(20_000, 8, 7, generator=g) * 0.3 - 2.5
    a = laplace_sample(mu, beta, torch.Generator().manual_seed(1), scale=1.5, exploration="chunk")
    eta = (a - mu) / (1.5 * beta.exp())
    assert float((eta - eta[:, :1]).abs().max()) < 1e-4  # held for the chunk's 8 steps
    assert abs(eta[:, 0].abs().mean().item() - 1.0) < 0.02 and abs(eta[:, 0].median().item()) < 0.02  # Laplace(0, 1)
    lp = chunk_log_prob(a, mu, beta, 1.5, "chunk")
    assert lp.shape == (20_000, 8) and torch.equal(lp, lp[:, :1].expand_as(lp))
    own = laplace_log_prob(eta[:, 0], torch.zeros(7), torch.zeros(7)) - (beta + math.log(1.5)).mean(1).sum(-1)
    torch.testing.assert_close(lp[:, 0], own, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(chunk_log_prob(a, mu, beta, 1.5, "step"), laplace_log_prob(a, mu, beta + math.log(1.5)))
    # a per-step draw is not one held offset: 8 independent ones per chunk
    step = (laplace_sample(mu, beta, torch.Generator().manual_seed(1)) - mu) / beta.exp()
    assert float((step - step[:, :1]).abs().mean()) > 0.5
    for bad in (lambda: laplace_sample(mu, beta, exploration="episode"),
                lambda: chunk_log_prob(a, mu, beta, 1.0, "episode")):
        with pytest.raises(ValueError, match="exploration must be one of"):
            bad()


def test_the_held_draws_score_moves_the_whole_chunk_along_the_offset_tried():
    """The gradient of a chunk-held draw's log-probability with respect to the means is
    sign(eta) / (K b_k) at every step k: the credit goes to the chunk's mean offset, once."""
    from worldenv_core.models.laplace import chunk_log_prob

    mu = torch.zeros(1, 8, 7, requires_grad=True)
    beta = torch.full((1, 8, 7), math.log(0.1))
    a = laplace_sample(mu.detach(), beta, torch.Generator().manual_seed(3), exploration="chunk")
    chunk_log_prob(a, mu, beta, 1.0, "chunk")[:, 0].sum().backward()
    expected = torch.sign(a[:, :1] - 0.0).expand(1, 8, 7) / (8 * 0.1)
    torch.testing.assert_close(mu.grad, expected)
