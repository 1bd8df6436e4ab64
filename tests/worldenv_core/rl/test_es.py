"""Evolution strategies in weight space: directions named by seeds, antithetic members, ARS's step."""
import copy

import pytest
import torch
from torch import nn

from worldenv_core.rl import es


class Tiny(nn.Module):
    """The policy's parameter names where they matter: the scale head is never moved."""

    def __init__(self):
        super().__init__()
        self.backbone = nn.Linear(3, 4)
        self.trunk = nn.Linear(4, 4)
        self.action_head = nn.Linear(4, 2)
        self.scale_head = nn.Linear(4, 2)


def test_a_direction_is_rebuilt_from_its_seed_and_scaled_by_each_tensors_rms():
    torch.manual_seed(0)
    m = Tiny()
    with torch.no_grad():
        m.trunk.weight.mul_(10.0)
    a, b = es.directions(m, 7), es.directions(m, 7)
    assert all(x.equal(y) for x, y in zip(a, b)) and not es.directions(m, 8)[0].equal(a[0])
    names = [n for n, _ in es.es_parameters(m)]
    assert not any(n.startswith("scale_head") for n in names)
    assert [n for n, _ in es.es_parameters(m, "heads")] == ["trunk.weight", "trunk.bias", "action_head.weight",
                                                             "action_head.bias"]
    big, small = a[names.index("trunk.weight")], a[names.index("backbone.weight")]
    assert big.std() > 4 * small.std()  # relative noise: the tensor 10x larger gets ~10x the move
    with pytest.raises(ValueError, match="es_parameters must be one of"):
        es.es_parameters(m, "all")


def test_members_are_antithetic_and_rebuilt_exactly_from_the_base():
    torch.manual_seed(0)
    m = Tiny()
    (s1, c1), (s2, c2) = es.antithetic_members([5], 0.1)
    assert s1 == s2 == 5 and c1 == -c2 == 0.1
    plus, minus = es.perturb(copy.deepcopy(m), s1, c1), es.perturb(copy.deepcopy(m), s2, c2)
    for (n, p), (_, q), (_, r) in zip(m.named_parameters(), plus.named_parameters(), minus.named_parameters()):
        if n.startswith("scale_head"):
            assert p.equal(q) and p.equal(r)
        else:
            assert torch.allclose((q + r) / 2, p, atol=1e-6) and not q.equal(p)
    with pytest.raises(ValueError, match="es_sigma must be > 0"):
        es.antithetic_members([1], 0.0)


def test_member_returns_are_successes_or_discounted_successes():
    success = torch.tensor([[1, 0], [1, 1]]).bool()
    steps = torch.tensor([[10, 50], [20, 5]])
    assert es.member_returns(success, steps).tolist() == [1.0, 0.5]
    r = es.member_returns(success, steps, 0.9)
    assert torch.allclose(r, torch.tensor([(0.9 ** 10 + 0.9 ** 20) / 2, 0.9 ** 5 / 2]))
    with pytest.raises(ValueError, match="es_discount"):
        es.member_returns(success, steps, 0.0)
    score = torch.tensor([[0.95, 0.4], [0.9, 0.1]])  # rl.es_return=score: the reflector's R replaces the verdict
    assert torch.allclose(es.member_returns(success, steps, score=score), torch.tensor([0.925, 0.25]))
    assert torch.allclose(es.context_returns(success, steps, 0.9, score)[0], torch.tensor([0.95 * 0.9 ** 10, 0.4 * 0.9 ** 50]))


def test_ars_climbs_a_smooth_objective_and_makes_no_step_without_a_difference():
    """Success probability a logistic function of the action head's bias: ARS with antithetic members
    and noisy (Bernoulli, shared contexts) returns raises it; equal returns move nothing."""
    torch.manual_seed(0)
    m = Tiny()
    target = torch.tensor([1.0, -1.0])

    def p_success(model):
        return torch.sigmoid(-4 * (model.action_head.bias - target).pow(2).sum())

    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        before = float(p_success(m))
    for it in range(60):
        seeds = torch.randint(2**62, (8,), generator=g).tolist()
        members = es.antithetic_members(seeds, 0.3)
        probs = torch.stack([p_success(es.perturb(copy.deepcopy(m), s, c)) for s, c in members]).detach()
        u = torch.rand(32, 1, generator=g)  # common random numbers: the same 32 contexts for every member
        success = u < probs[None]
        es.ars_update(m, seeds, es.member_returns(success, torch.zeros_like(success, dtype=torch.long)), 0.3,
                      top=4)
    with torch.no_grad():
        assert float(p_success(m)) > before + 0.3
    frozen = copy.deepcopy(m)
    stats = es.ars_update(m, [1, 2], torch.tensor([0.5, 0.5, 0.5, 0.5]), 0.3)
    assert stats["es_step_rms"] == 0.0 and all(p.equal(q) for p, q in zip(m.parameters(), frozen.parameters()))
    with pytest.raises(ValueError, match="es_step must be > 0"):
        es.ars_update(m, [1], torch.tensor([1.0, 0.0]), 0.0)


def test_a_context_tells_members_apart_only_where_their_outcomes_differ():
    success = torch.tensor([[1, 1, 1, 1], [0, 0, 0, 0], [1, 0, 1, 1], [0, 0, 1, 0]])
    assert es.mixed_contexts(success) == 2 and es.mixed_contexts(success[:2]) == 0
    # a discounted return tells apart members that all succeeded, by when; not those that all failed
    steps = torch.tensor([[40, 48, 40, 40], [64, 64, 64, 64], [40, 64, 40, 40], [64, 64, 56, 64]])
    assert es.mixed_contexts(es.context_returns(success.bool(), steps, 0.97)) == 3
    assert es.mixed_contexts(es.context_returns(success.bool(), steps, 1.0)) == 2
    # graded scores: a spread above SCORE_APART, verdicts aside
    score = torch.tensor([[0.9, 0.9, 0.9, 0.9], [0.1, 0.1 + 2 * es.SCORE_APART, 0.1, 0.1], [0.5, 0.52, 0.5, 0.5],
                          [0.2, 0.2, 0.2, 0.8]])
    assert es.mixed_contexts(score, es.SCORE_APART) == 2


def test_the_ledger_rebuilds_the_runs_weights_from_the_starting_policy(tmp_path):
    """Each iteration's record (contexts, seeds, outcomes, settings) replayed on the starting policy gives the
    run's weights exactly; a missing iteration is named."""
    from omegaconf import OmegaConf

    torch.manual_seed(0)
    start = Tiny()
    run = copy.deepcopy(start)
    rl = OmegaConf.create({"es_sigma": 0.1, "es_step": 0.2, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})
    g = torch.Generator().manual_seed(3)
    for it in (1, 2, 3):
        seeds = torch.randint(2**62, (2,), generator=g).tolist()
        success = torch.rand(5, 4, generator=g) < 0.5
        steps = torch.randint(1, 40, (5, 4), generator=g)
        returns = es.member_returns(success, steps)
        es.ars_update(run, seeds, returns, rl.es_step, rl.es_top, rl.es_parameters)
        es.write_ledger_entry(tmp_path, it, [it, it + 1], seeds, success, steps, returns, rl, focus_task=it - 1)
    entries = es.read_ledger(tmp_path)
    assert [e["iteration"] for e in entries] == [1, 2, 3] and len(entries[0]["success"]) == 5
    assert [e["focus_task"] for e in entries] == [0, 1, 2]  # the task each trained, beside its 1-based number
    rebuilt = es.replay_ledger(copy.deepcopy(start), entries)
    assert all(p.equal(q) for p, q in zip(rebuilt.parameters(), run.parameters()))
    assert not all(p.equal(q) for p, q in zip(es.replay_ledger(copy.deepcopy(start), entries, 2).parameters(),
                                              run.parameters()))
    (tmp_path / "iter_0002.json").unlink()
    with pytest.raises(ValueError, match="iteration 2 is missing"):
        es.read_ledger(tmp_path)


def test_a_ledger_names_its_starting_weights_and_refuses_others(tmp_path):
    """The digest covers every weight and buffer; a folder that names other starting weights is refused (its steps
    would make another policy), one that names none (before the record) is taken as it is."""
    torch.manual_seed(0)
    start = Tiny()
    digest = es.weights_digest(start)
    assert digest == es.weights_digest(copy.deepcopy(start)) and len(digest) == 16
    es.check_start(tmp_path, "0" * 16)  # no start.json: nothing to check
    es.record_start(tmp_path, digest)
    es.record_start(tmp_path, "f" * 16)  # once: the first export names it
    es.check_start(tmp_path, digest)
    other = copy.deepcopy(start)
    with torch.no_grad():
        other.trunk.bias[0] += 1e-6
    with pytest.raises(ValueError, match=f"made on starting weights {digest}"):
        es.check_start(tmp_path, es.weights_digest(other))


def test_half_agreement_is_high_where_directions_matter_and_near_zero_where_they_do_not():
    """Simulated ledgers: pairs whose members truly differ agree between the even and the odd starts; pairs
    whose outcomes are coin flips do not (pooled over many iterations)."""
    g = torch.Generator().manual_seed(0)

    def ledger(effect: float) -> list[dict]:
        out = []
        for _ in range(40):
            p = 0.5 + effect * torch.randn(4, generator=g).clamp(-1.5, 1.5)  # pair k's members: p_k and 1 - p_k
            probs = torch.stack([p, 1 - p], 1).flatten()
            success = torch.rand(32, 8, generator=g) < probs[None]
            out.append({"success": success.int().tolist(), "steps": torch.ones(32, 8).int().tolist()})
        return out
    signal, noise = es.half_agreement(ledger(0.25)), es.half_agreement(ledger(0.0))
    assert signal["pooled"] > 0.6 and abs(noise["pooled"]) < 0.2 and len(signal["per_iteration"]) == 40


def test_a_shaped_return_judged_by_success_finds_the_direction_speed_carries():
    """Simulated ledgers where each direction changes success a little and speed a lot: differences measured with
    a discount point where the odd starts' successes do more clearly than successes judged by successes; where the
    faster member fails more often, the discounted differences point against success."""
    g = torch.Generator().manual_seed(1)

    def ledger(speed_sign: float) -> list[dict]:
        out = []
        for _ in range(40):
            effect = torch.randn(4, generator=g)
            p = 0.5 + 0.06 * effect  # pair k's members: p_k and 1 - p_k, barely apart
            probs = torch.stack([p, 1 - p], 1).flatten()
            success = torch.rand(16, 8, generator=g) < probs[None]
            pace = torch.stack([effect, -effect], 1).flatten() * speed_sign  # the + member faster where it helps
            steps = (150 - 40 * pace[None] + 10 * torch.randn(16, 8, generator=g)).clamp(20, 300).round()
            out.append({"success": success.int().tolist(), "steps": steps.int().tolist()})
        return out
    aligned, opposed = ledger(1.0), ledger(-1.0)
    plain = es.half_agreement(aligned)["pooled"]
    shaped = es.half_agreement(aligned, 0.98, judged_by=1.0)
    assert shaped["pooled"] > plain + 0.1 and len(shaped["per_iteration"]) == 40
    assert es.half_agreement(opposed, 0.98, judged_by=1.0)["pooled"] < 0
    assert es.half_agreement(aligned, 1.0, judged_by=1.0)["pooled"] == pytest.approx(plain, abs=0.02)  # both ways round


def test_halves_split_every_task_between_them():
    assert es.halves([10, 11, 12, 13, 14, 15], 2).tolist() == [0, 0, 1, 1, 0, 0]
    assert es.halves([10, 11, 12, 13], 2, across_tasks=True).tolist() == [0, 1, 0, 1]
    assert es.halves([7, 8, 9], 1).tolist() == [0, 1, 0]  # one task: even and odd positions
    with pytest.raises(ValueError, match="needs n_tasks >= 2"):
        es.half_agreement([], across_tasks=True)
