"""The weight-space update's iteration (no simulator): members' rollouts in an imagined environment whose
verdict is known, the ARS step, and the paired-replay guard undoing a step (and the ledger saying so)."""
import copy

import torch
from omegaconf import OmegaConf

from stages.post_train_loop.es_update import es_phase
from tests.worldenv_core.rl.test_loop import ActionRewardEnv, _policy_and_contexts
from worldenv_core.rl import es


class VerdictEnv(ActionRewardEnv):
    """ActionRewardEnv whose verdict is a success where at least half of a rollout's x-actions were > 0."""

    def step(self, actions, generator=None):
        state = super().step(actions, generator)
        state.by_reflector = state.done & (state.reward >= 0.5)
        return state


RL = {"iterations": 1, "contexts_per_iteration": 4, "es_pairs": 3, "es_sigma": 0.5, "es_step": 0.5, "es_top": None,
      "es_discount": 1.0, "es_parameters": "mean", "guard_max_hack_rate": 0.5}


def test_each_member_acts_with_its_own_weights_in_one_batch_through_the_imagined_env():
    policy, contexts, encoder = _policy_and_contexts(3)
    members = es.antithetic_members([11, 12], 0.5)
    out = es.imagined_member_outcomes(policy, VerdictEnv(), contexts, members, encoder)
    assert out["success"].shape == out["steps"].shape == out["reward"].shape == (3, 4) and out["episodes"] == 0
    assert torch.equal(out["success"], out["reward"] >= 0.5)  # the graded verdict behind each success
    for m, (seed, coef) in enumerate(members):  # the same member alone, in a batch of its own
        alone = es.imagined_member_outcomes(es.perturb(copy.deepcopy(policy), seed, coef), VerdictEnv(), contexts,
                                            [(seed, 0.0)], encoder)
        assert torch.equal(alone["success"][:, 0], out["success"][:, m])
    assert 0 < out["success"].float().mean() < 1  # the members differ: something for the step to follow


def test_the_guard_undoes_a_step_and_the_ledger_replays_without_it(tmp_path):
    rl = OmegaConf.create(RL)
    for hack_rate, undone in ((1.0, True), (0.0, False)):
        policy, contexts, encoder = _policy_and_contexts(4)
        start = copy.deepcopy(policy)
        collect = lambda base, picks, members: es.imagined_member_outcomes(  # noqa: E731
            base, VerdictEnv(), [contexts[i] for i in picks], members, encoder)
        ledger = tmp_path / f"ledger_{undone}"
        phase = es_phase(policy, collect, 4, rl, 0, ledger, guard=lambda p: {"guard_hack_rate": hack_rate,
                                                                            "guard_episodes": 2})
        stats = phase.step(next(iter(phase.batches(0))))
        assert stats["es_return_std"] > 0 and stats["guard_episodes"] == 2
        same = all(a.equal(b) for a, b in zip(policy.parameters(), start.parameters()))
        assert same == undone and stats.get("rolled_back", 0.0) == float(undone)
        (entry,) = es.read_ledger(ledger)
        assert entry.get("rolled_back", False) == undone
        replayed = es.replay_ledger(copy.deepcopy(start), [entry])
        assert all(a.equal(b) for a, b in zip(replayed.parameters(), policy.parameters()))


def test_no_step_from_too_few_telling_contexts_and_the_ledger_replays_it_as_none(tmp_path):
    """rl.es_min_mixed: an iteration in which fewer contexts told the members apart makes no step; the ledger
    marks it, and a replay leaves the weights where the run left them."""
    for min_mixed in (1, 5):  # 4 contexts: at most 4 can tell the members apart
        rl = OmegaConf.create({**RL, "es_min_mixed": min_mixed})
        policy, contexts, encoder = _policy_and_contexts(4)
        start = copy.deepcopy(policy)
        collect = lambda base, picks, members: es.imagined_member_outcomes(  # noqa: E731
            base, VerdictEnv(), [contexts[i] for i in picks], members, encoder)
        ledger = tmp_path / f"ledger_{min_mixed}"
        stats = (phase := es_phase(policy, collect, 4, rl, 0, ledger)).step(next(iter(phase.batches(0))))
        assert 1 <= stats["es_mixed_contexts"] <= 4
        moved = not all(a.equal(b) for a, b in zip(policy.parameters(), start.parameters()))
        assert moved == (min_mixed == 1) and stats.get("no_step", 0.0) == float(min_mixed == 5)
        (entry,) = es.read_ledger(ledger)
        assert entry.get("no_step", False) == (min_mixed == 5)
        replayed = es.replay_ledger(copy.deepcopy(start), [entry])
        assert all(a.equal(b) for a, b in zip(replayed.parameters(), policy.parameters()))


def test_a_campaign_folder_is_kept_current_and_an_interrupted_sitting_still_fills_it(tmp_path):
    """rl.es_ledger_from: the yielded after_save exports the ledger; an interrupt exports it once more before going
    on up; a run with no campaign folder (or not ES) gets nothing to call."""
    import pytest

    from stages.post_train_loop.es_update import campaign_ledger

    rl = OmegaConf.create({"policy_update": "es", "es_ledger_from": str(tmp_path / "kept"), "es_sigma": 0.05,
                           "es_step": 0.05, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})
    work = tmp_path / "work"
    es.write_ledger_entry(work / "es_ledger", 1, [3, 4], [7], torch.ones(2, 2), torch.full((2, 2), 9),
                          torch.ones(2), rl)
    with campaign_ledger(work, rl) as keep:
        keep(1)
    assert es.read_ledger(tmp_path / "kept")[0]["seeds"] == [7]
    es.write_ledger_entry(work / "es_ledger", 2, [5, 6], [8], torch.zeros(2, 2), torch.full((2, 2), 9),
                          torch.zeros(2), rl)
    with pytest.raises(KeyboardInterrupt), campaign_ledger(work, rl):
        raise KeyboardInterrupt
    assert [e["seeds"] for e in es.read_ledger(tmp_path / "kept")] == [[7], [8]]
    for other in ({**rl, "es_ledger_from": None}, {**rl, "policy_update": "ppo"}):
        with campaign_ledger(work, OmegaConf.create(other)) as keep:
            assert keep is None


def test_the_score_return_steps_where_no_verdict_splits_and_the_ledger_keeps_the_scores(tmp_path):
    """rl.es_return=score: each member's return is its rollouts' graded verdict (the reflector's R), so the step
    follows the members' scores although every verdict is the same; the ledger keeps the scores beside the verdicts
    and the settings, and replays the step exactly."""
    class NoSuccessEnv(ActionRewardEnv):  # the graded reward as before, but no rollout is ever judged a success
        def step(self, actions, generator=None):
            state = super().step(actions, generator)
            state.by_reflector = torch.zeros_like(state.done)
            return state

    for ret, moves in (("success", False), ("score", True)):
        rl = OmegaConf.create({**RL, "es_return": ret, "es_min_mixed": 1})
        policy, contexts, encoder = _policy_and_contexts(4)
        start = copy.deepcopy(policy)
        collect = lambda base, picks, members: es.imagined_member_outcomes(  # noqa: E731
            base, NoSuccessEnv(), [contexts[i] for i in picks], members, encoder)
        ledger = tmp_path / ret
        stats = (phase := es_phase(policy, collect, 4, rl, 0, ledger)).step(next(iter(phase.batches(0))))
        moved = not all(a.equal(b) for a, b in zip(policy.parameters(), start.parameters()))
        assert moved == moves and (stats["es_mixed_contexts"] > 0) == moves
        (entry,) = es.read_ledger(ledger)
        assert entry["es_return"] == ret and ("score" in entry) == moves
        if moves:
            assert torch.allclose(torch.tensor(entry["returns"]), torch.tensor(entry["score"]).mean(0), atol=1e-3)
        replayed = es.replay_ledger(copy.deepcopy(start), [entry])
        assert all(a.equal(b) for a, b in zip(replayed.parameters(), policy.parameters()))
