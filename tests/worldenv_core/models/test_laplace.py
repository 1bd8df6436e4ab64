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
