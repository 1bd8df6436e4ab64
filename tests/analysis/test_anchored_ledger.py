import torch
from omegaconf import OmegaConf

from analysis.anchored_ledger import anchored_replay, own_tasks
from tests.worldenv_core.rl.test_anchor import TinyPolicy, frames
from worldenv_core.rl import es
from worldenv_core.rl.anchor import mean_actions


def ledger(tmp_path, policy):
    """Two iterations written as a run writes them: the first on task 0's placements, the second on task 1's."""
    rl = OmegaConf.create({"es_sigma": 0.1, "es_step": 0.3, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})
    g = torch.Generator().manual_seed(3)
    for it, contexts in ((1, [10, 12, 14]), (2, [21, 23, 25])):
        seeds = torch.randint(2**62, (3,), generator=g).tolist()
        success, steps = torch.rand(3, 6, generator=g) < 0.5, torch.randint(1, 40, (3, 6), generator=g)
        es.write_ledger_entry(tmp_path, it, contexts, seeds, success, steps, es.member_returns(success, steps), rl)
    return es.read_ledger(tmp_path)


def test_an_iterations_task_is_its_placements():
    assert own_tasks([10, 20, 30], 10) == {0} and own_tasks([3, 4, 13], 10) == {3, 4}


def test_without_anchoring_the_replay_is_the_ledgers_and_anchoring_keeps_each_step_on_its_task(tmp_path):
    torch.manual_seed(0)
    start, data = TinyPolicy(), frames()
    entries = ledger(tmp_path / "ledger", start)
    plain, anchored = TinyPolicy(), TinyPolicy()
    for m in (plain, anchored):
        m.load_state_dict(start.state_dict())
    es.replay_ledger(plain, entries)
    zero = TinyPolicy()
    zero.load_state_dict(start.state_dict())
    steps = anchored_replay(zero, entries, data, n_tasks=2, iterations=0, log=lambda _: None)
    assert [s["tasks"] for s in steps] == [[0], [1]]
    assert all(torch.allclose(a, b) for a, b in zip(zero.parameters(), plain.parameters()))
    steps = anchored_replay(anchored, entries, data, n_tasks=2, iterations=600, lr=3e-3, batch=64, log=lambda _: None)
    assert all(s["anchor_left_other"] < 0.5 for s in steps)
    # the first step, measured on task 0, no longer moves task 1's actions as the plain replay's does
    first = TinyPolicy()
    first.load_state_dict(start.state_dict())
    es.replay_ledger(first, entries, upto=1)
    other = data.task_ids == 1
    moved_plain = (mean_actions(first, data) - mean_actions(start, data))[other].abs().mean()
    again = TinyPolicy()
    again.load_state_dict(start.state_dict())
    anchored_replay(again, entries, data, n_tasks=2, upto=1, iterations=600, lr=3e-3, batch=64, log=lambda _: None)
    moved_anchored = (mean_actions(again, data) - mean_actions(start, data))[other].abs().mean()
    assert moved_anchored < 0.5 * moved_plain
