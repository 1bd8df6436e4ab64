import pytest
import torch

from worldenv_core.rl import es
from worldenv_core.rl.anchor import AnchorFrames, anchored_step, mean_actions


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
    return AnchorFrames({"cam": torch.zeros(n, 3, 4, 4, dtype=torch.uint8)}, torch.randn(n, 4, generator=g),
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
