"""Paired replay's real side: a recorded action sequence executed again from a recorded frame
reproduces the recorded outcome and frames (the premise of measuring the imagined verdict)."""
import numpy as np
import pytest

from worldenv_core.data.mcap_io import read_episode
from worldenv_core.envs.recording import cached_env
from worldenv_core.envs.replay import (PairedReplayJob, RealStart, ReplayError, by_start, execute, replay_context,
                                     restore)

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def demo(demo_experiment):
    """A recorded expert demo of the tiny task (it succeeds, then acts 8 steps more)."""
    path = sorted((demo_experiment / "data").rglob("*.mcap"))[0]
    return path, read_episode(path)


def test_replaying_a_recorded_episode_from_a_middle_frame_reproduces_its_outcome_and_frames(demo, contract):
    path, ep = demo
    c = contract()
    env = cached_env(c.suite, ep.meta.task_id, c.cameras, c.image_size)
    for f in (0, 17):
        start = RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=f)
        out = execute(env, start, ep.actions[f:], every=c.chunk, camera="agentview")
        assert out["error"] is None and out["steps"] == ep.length - f
        first = int(np.flatnonzero(ep.success)[0])
        assert out["success"] and out["first_success"] == first - f  # the same step as recorded
        assert out["success_at_end"] == bool(ep.success[-1])
        for t, img in out["frames"].items():  # every rendered chunk boundary, the same image: physics replays
            diff = np.abs(img.astype(int) - ep.images["agentview"][f + t])  # to ~1e-7, which moves a pixel or two
            assert diff.max() <= 1 and (diff > 0).sum() <= 4, f"frame {f + t} differs"  # by one grey level at most
        # the start, every chunk boundary up to the end, and the end
        assert len(out["frames"]) == len(range(0, ep.length - f + 1, c.chunk)) + ((ep.length - f) % c.chunk != 0)


def test_other_actions_change_the_outcome_and_a_wrong_prefix_is_caught(demo, contract):
    path, ep = demo
    c = contract()
    env = cached_env(c.suite, ep.meta.task_id, c.cameras, c.image_size)
    start = RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=10)
    idle = np.zeros((24, 7), np.float32)
    idle[:, 6] = -1.0
    out = execute(env, start, idle, every=c.chunk, camera="agentview", keep=frozenset({8}))
    assert not out["success"] and out["first_success"] is None and set(out["frames"]) == {8}
    # a replay that ends away from the recorded state is an error, never a silent mismatch (frame 10 is now kept:
    # the gap measured when it was replayed is checked again)
    with pytest.raises(ReplayError, match="away from the recorded state"):
        restore(env, RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=10), tolerance=-1)


def test_a_keyframe_met_again_is_put_back_without_replaying_and_leads_where_the_replay_did(demo, contract,
                                                                                           monkeypatch):
    """ES members start from the same keyframe one after another: the env replays the recorded actions to it once,
    then puts the kept point back (no episode read, no steps), and the recorded actions from there reach the same
    outcome and frames."""
    import worldenv_core.data.mcap_io as mcap_io

    path, ep = demo
    c = contract()
    env = cached_env(c.suite, ep.meta.task_id, c.cameras, c.image_size)
    start = RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=13)
    first = execute(env, start, ep.actions[13:], every=c.chunk, camera="agentview")
    reads = []
    monkeypatch.setattr(mcap_io, "read_episode", lambda *a, **k: reads.append(a) or ep)
    again = execute(env, start, ep.actions[13:], every=c.chunk, camera="agentview")
    assert reads == []  # put back, not replayed
    assert again["first_success"] == first["first_success"] == int(np.flatnonzero(ep.success)[0]) - 13
    for t, img in first["frames"].items():
        assert np.abs(img.astype(int) - again["frames"][t]).max() <= 1, f"frame {t} differs"


def test_a_replay_job_returns_one_real_outcome_per_action_sequence(demo, contract):
    path, ep = demo
    start = RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=5)
    job = PairedReplayJob(contract(), start, actions=(ep.actions[5:], ep.actions[5:9]), keep=((8,), None))
    out = replay_context(job)
    assert out["start"] == start and out["closed_loop"] == []
    assert [r["success"] for r in out["replays"]] == [True, False]
    assert set(out["replays"][0]["frames"]) == {8} and set(out["replays"][1]["frames"]) == {0, 4}


def test_the_real_side_scores_a_mid_episode_replay_with_the_recorded_past(demo, contract, tmp_path):
    """The reflector judging a replay from frame f is shown the recorded frames before f at the chunk spacing, as
    the imagined side's is (`Context.history`): its first score is that of the whole recorded prefix."""
    import torch
    from hydra.utils import instantiate

    from tests.worldenv_core.models.test_reflector import small_config
    from worldenv_core.models.checkpoint import save_model
    from worldenv_core.models.text import InstructionEncoder

    path, ep = demo
    c = contract()
    cfg = {**small_config(max_frames=8, input_size=32), "instruction_dim": 384}  # the instruction encoder's width
    cfg["frame_encoder"] = {**cfg["frame_encoder"], "cond_dim": 384}
    model = instantiate(cfg).eval()
    save_model(tmp_path / "r", model, cfg, {"kind": "reflector", "image_size": c.image_size, "camera": "agentview"})
    f = 2 * c.chunk + 1
    start = RealStart(task_id=ep.meta.task_id, seed=ep.meta.seed, episode=str(path), frame=f)
    out = replay_context(PairedReplayJob(c, start, actions=(ep.actions[f:f + c.chunk],), keep=(None,),
                                         reflector_path=str(tmp_path / "r")))
    images = torch.from_numpy(ep.images["agentview"]).permute(0, 3, 1, 2)
    lang = InstructionEncoder()([ep.meta.instruction])[0]
    with_past = model.score_video(images[[1, 1 + c.chunk, f]], lang)
    assert out["replays"][0]["scores"][0] == pytest.approx(float(with_past), abs=1e-4)
    assert out["replays"][0]["scores"][0] != pytest.approx(float(model.score_video(images[[f]], lang)), abs=1e-4)


def test_each_benchmark_init_state_has_its_own_key_per_task_and_a_repeated_key_is_refused():
    # init state 0 of task 0 and of task 1 are two contexts: keyed alike, one task's replays once stood for both
    starts = [RealStart(task_id=t, init_state=i) for t in (0, 1) for i in (0, 1)]
    assert len({s.key for s in starts}) == 4
    assert RealStart(task_id=0, episode="d/e.mcap", frame=3).key == "d/e.mcap@3"
    got = by_start([{"start": s, "replays": [k]} for k, s in enumerate(starts)])
    assert [got[s.key]["replays"] for s in starts] == [[0], [1], [2], [3]]
    with pytest.raises(ValueError, match="cannot be told apart"):
        by_start([{"start": starts[0]}, {"start": RealStart(task_id=0, init_state=0)}])
