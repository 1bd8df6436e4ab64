"""WorldModelView: the policy sees real frames as the world model renders imagined ones."""
import numpy as np
import pytest
import torch

from tests.worldenv_core.imagination.conftest import TINY, camera
from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.imagination.view import WorldModelView
from worldenv_core.kinematics import NextStateModel
from worldenv_core.models.worldsim import WorldSimulator


class Recorder:
    """A policy runner that keeps what it was shown."""
    cameras = ["agentview"]
    encoder = generator = None

    def __init__(self):
        self.seen = []

    def act_chunk(self, images, proprio, instruction):
        self.seen.append(images["agentview"])
        return np.zeros((4, 7)), np.zeros((4, 7)), np.zeros((4, 7))


class Acting(Recorder):
    """A policy runner that moves (the same chunk every time) and keeps the proprio it was shown."""

    def act_chunk(self, images, proprio, instruction):
        self.seen.append(np.asarray(proprio))
        return np.full((4, 7), 0.5), np.zeros((4, 7)), np.zeros((4, 7))


def frames(n, seed=0):
    return [np.random.default_rng(seed + i).integers(0, 255, (32, 32, 3), dtype=np.uint8) for i in range(n)]


def make_view(detail_gate):
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0), detail_gate=detail_gate)
    return WorldModelView(Recorder(), sim, "agentview"), sim


@pytest.mark.parametrize("detail_gate", [0.0, 0.1])
def test_first_frame_as_it_is_later_ones_as_imagined(detail_gate):
    view, sim = make_view(detail_gate)
    first, second, third = frames(3)
    for f in (first, second, third):
        view.act_chunk({"agentview": f}, np.zeros(7), "task")
    seen = view.runner.seen
    assert np.array_equal(seen[0], first)  # the context frame, as imagination shows it
    with torch.no_grad():  # later frames: encoded, then rendered as an imagined latent (detail from the first)
        expect = sim.render(sim.model.encode(torch.as_tensor(third).permute(2, 0, 1)[None, None]))[0, 0]
    assert np.array_equal(seen[2], (expect * 255).round().to(torch.uint8).permute(1, 2, 0).numpy())
    assert not np.array_equal(seen[1], second) and seen[1].shape == second.shape and seen[1].dtype == np.uint8


def test_new_episode_takes_a_new_anchor():
    view, _ = make_view(0.1)
    a, b = frames(2), frames(2, seed=10)
    for f in a:
        view.act_chunk({"agentview": f}, np.zeros(7), "task")
    view.new_episode()
    view.act_chunk({"agentview": b[0]}, np.zeros(7), "task")
    assert np.array_equal(view.runner.seen[-1], b[0])


def test_a_camera_the_policy_does_not_see_is_refused():
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    with pytest.raises(ValueError, match="does not see"):
        WorldModelView(Recorder(), sim, "wrist")


def test_proprio_is_the_kinematic_models_through_the_executed_chunks():
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))

    view = WorldModelView(Acting(), sim, "agentview", parts=("proprio",))
    start = np.array([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0])
    image = frames(1)[0]
    for _ in range(3):  # the real state stays at the start: what the policy sees moves with the actions
        view.act_chunk({"agentview": image}, start, "task")
    seen = view.runner.seen
    assert np.array_equal(seen[0], start)
    expect, carry = NextStateModel().rollout(torch.as_tensor(start)[None], torch.full((1, 4, 7), 0.5, dtype=torch.float64))
    expect, _ = NextStateModel().rollout(expect[:, -1], torch.full((1, 4, 7), 0.5, dtype=torch.float64), carry)
    np.testing.assert_allclose(seen[2], expect[0, -1].float().numpy(), rtol=1e-6)
    assert not np.allclose(seen[1], start)


def test_unknown_view_parts_are_refused():
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    with pytest.raises(ValueError, match="view parts"):
        WorldModelView(Recorder(), sim, "agentview", parts=("depth",))


def test_pose_or_gripper_alone_keeps_the_rest_of_the_real_state():
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))

    start = np.array([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0])
    both = {}
    for parts in (("proprio",), ("pose",), ("gripper",)):
        view = WorldModelView(Acting(), sim, "agentview", parts=parts)
        for _ in range(2):
            view.act_chunk({"agentview": frames(1)[0]}, start, "task")
        both[parts[0]] = view.runner.seen[1]
    np.testing.assert_allclose(both["pose"][:6], both["proprio"][:6])
    np.testing.assert_allclose(both["pose"][6], start[6])
    np.testing.assert_allclose(both["gripper"][6], both["proprio"][6])
    np.testing.assert_allclose(both["gripper"][:6], start[:6], atol=1e-6)
    assert both["proprio"][6] != start[6]
