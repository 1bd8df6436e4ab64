import pytest
import torch
from omegaconf import OmegaConf

from analysis.anchored_ledger import anchored_replay, anchored_step, own_tasks
from analysis.policy_frames import PolicyFrames, mean_actions
from worldenv_core.rl import es


class TinyPolicy(torch.nn.Module):
    """The policy's interface, (images, proprio, instruction) -> (mean chunk, scale), with a hidden layer
    the tasks share: a step on one task moves the other's actions, and anchoring can undo that."""

    def __init__(self):
        super().__init__()
        self.trunk = torch.nn.Sequential(torch.nn.Linear(4 + 2, 16), torch.nn.Tanh())
        self.action_head = torch.nn.Linear(16, 2 * 3)
        self.scale_head = torch.nn.Linear(16, 2 * 3)

    def forward(self, images, proprio, instruction):
        h = self.trunk(torch.cat([proprio, instruction], -1) + 0 * images["cam"].float().mean((1, 2, 3))[:, None])
        return self.action_head(h).view(-1, 2, 3), self.scale_head(h).view(-1, 2, 3)


def frames(n=64):
    g = torch.Generator().manual_seed(1)
    tasks = torch.arange(n) % 2
    return PolicyFrames({"cam": torch.zeros(n, 3, 4, 4, dtype=torch.uint8)}, torch.randn(n, 4, generator=g),
                        torch.nn.functional.one_hot(tasks, 2).float(), tasks)


def test_the_step_stays_on_its_task_and_leaves_the_other():
    torch.manual_seed(0)
    policy, data = TinyPolicy(), frames()
    before = mean_actions(policy, data)
    stats = anchored_step(policy, lambda p: {"stepped": float(bool(es.perturb(p, 7, 0.2)))}, data, {0},
                          iterations=1500, lr=3e-3, batch=64)
    after = mean_actions(policy, data)
    assert stats["stepped"] == 1.0 and stats["anchor_moved_other"] > 0.05 and stats["anchor_moved_own"] > 0.05
    assert stats["anchor_left_other"] < 0.2 and stats["anchor_own_error"] < 0.2
    other = data.task_ids == 1
    assert (after - before)[other].pow(2).mean().sqrt() < 0.2 * stats["anchor_moved_other"]
    # the scale head is not ES's and not anchored: untouched
    assert all(p.grad is None for p in policy.parameters())


def test_without_anchoring_iterations_the_step_is_the_plain_step():
    torch.manual_seed(0)
    a, data = TinyPolicy(), frames()
    b = TinyPolicy()
    b.load_state_dict(a.state_dict())
    stats = anchored_step(a, lambda p: es.perturb(p, 7, 0.2) and {}, data, {0}, iterations=0)
    es.perturb(b, 7, 0.2)
    assert all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters()))
    assert stats["anchor_left_other"] == pytest.approx(1.0)


def test_a_step_on_every_task_has_nothing_to_anchor():
    torch.manual_seed(0)
    policy, data = TinyPolicy(), frames()
    stats = anchored_step(policy, lambda p: es.perturb(p, 7, 0.2) and {}, data, {0, 1}, iterations=50)
    assert stats["anchor_own_error"] == 0.0 and stats["anchor_moved_other"] != stats["anchor_moved_other"]  # NaN


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
