"""Failure modes read off the gripper's opening: grasps, their outcome, the phase at a keyframe."""
import json

import numpy as np
import pytest
import torch

from analysis.failure_modes import classify, failure_modes, grasps, main, phase_at, table


def trace(*segments):
    """An opening trace from (value, frames) segments."""
    return np.concatenate([np.full(n, v, dtype=np.float32) for v, n in segments])


OPEN, BOWL, NOTHING = 0.98, 0.13, 0.02
EMPTY_THEN_HELD = trace((OPEN, 20), (NOTHING, 12), (OPEN, 10), (BOWL, 30), (OPEN, 10))


def test_grasps_are_closures_that_last():
    assert grasps(EMPTY_THEN_HELD) == [(20, 32), (42, 72)]
    assert grasps(trace((OPEN, 5), (NOTHING, 3), (OPEN, 5))) == []  # a blink of the fingers is no grasp
    assert grasps(trace((BOWL, 10))) == [(0, 10)]  # closed from the first frame to the last


def test_each_failure_is_named_by_what_its_grasps_held():
    assert classify(EMPTY_THEN_HELD, success=True) == ("success", 32)
    assert classify(EMPTY_THEN_HELD, success=False) == ("lost object", 32)
    assert classify(trace((OPEN, 20), (NOTHING, 30), (OPEN, 20)), success=False) == ("empty grasp", 50)
    assert classify(trace((OPEN, 50)), success=False) == ("no grasp", None)
    # a wider empty threshold reads the bowl's rim as nothing
    assert classify(EMPTY_THEN_HELD, success=False, empty_below=0.2) == ("empty grasp", 32)


def test_the_phase_at_a_keyframe():
    assert [phase_at(EMPTY_THEN_HELD, k) for k in (5, 25, 35, 60, 80)] == [
        "before a grasp", "closed on nothing", "after an empty grasp", "holding", "after a held grasp"]


def _episode(rng, opening, success, task, noise):
    from tests.conftest import synthetic_episode

    ep = synthetic_episode(rng, length=len(opening) - 1)
    ep.proprio[:, 6] = opening
    ep.meta.success, ep.meta.task_id, ep.meta.extra = success, task, {"noise_scale": noise}
    return ep


def test_counts_by_noise_and_task_and_the_keyframe_window(tmp_path):
    from worldenv_core.data.mcap_io import write_episode

    rng = np.random.default_rng(0)
    empty = trace((OPEN, 20), (NOTHING, 30), (OPEN, 50))  # its first empty grasp ends at frame 50 of 99 steps
    cases = [(EMPTY_THEN_HELD, True, 0, "1.0"), (empty, False, 0, "1.0"), (empty, False, 1, "2.5"),
             (EMPTY_THEN_HELD, False, 1, "2.5")]
    for i, (opening, success, task, noise) in enumerate(cases):
        write_episode(tmp_path / f"ep{i}.mcap", _episode(rng, opening, success, task, noise))
    paths = sorted(tmp_path.glob("ep*.mcap"))
    modes = failure_modes(paths, depth=(0.4, 0.7))
    assert modes["counts"] == {"success": 1, "empty grasp": 2, "lost object": 1} and modes["failures"] == 3
    assert modes["by_noise_scale"]["2.5"] == {"empty grasp": 1, "lost object": 1}
    assert modes["by_task"][0] == {"success": 1, "empty grasp": 1}
    # the two empty ones missed at 51 % (inside the window), the lost object at 32 / 81 = 40 % (at its start)
    assert modes["failures_missed_before"] == {"window start": pytest.approx(1 / 3), "window end": 1.0}

    run = {"worldsim": "w", "iterations": {"keyframes": {
        "keyframes": [f"{paths[1]}@40", f"{paths[3]}@60"], "real_by_context": [0.0, 0.75],
        "imagined_by_context": [1.0, 0.25]}}}
    (tmp_path / "run.json").write_text(json.dumps(run))
    out = main(["--keyframes", str(tmp_path / "run.json"), "--json", str(tmp_path / "phases.json")])
    rows = out[str(tmp_path / "run.json")]["contexts"]
    assert [r["phase"] for r in rows] == ["closed on nothing", "holding"] and rows[0]["imagined"] == 1.0
    assert json.loads((tmp_path / "phases.json").read_text()) == out


def test_bad_input_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no episode matched"):
        main(["--episodes", str(tmp_path / "none*.mcap")])
    with pytest.raises(ValueError, match="--depth must be"):
        main(["--episodes", "x", "--depth", "0.7", "0.3"])
    (tmp_path / "ledger.json").write_text(json.dumps({"iterations": {"1": {"real_by_context": []}}}))
    with pytest.raises(ValueError, match="no keyframes"):
        main(["--keyframes", str(tmp_path / "ledger.json")])


def test_the_success_models_verdicts_are_counted_per_kind(tmp_path):
    """A real (untrained, tiny) reflector judging the real frames: at eta 0 it stops every episode, at 1 none."""
    from hydra.utils import instantiate

    from tests.worldenv_core.imagination.conftest import REFLECTOR
    from worldenv_core.data.mcap_io import write_episode

    rng = np.random.default_rng(1)
    for i, (opening, success) in enumerate([(EMPTY_THEN_HELD, True), (EMPTY_THEN_HELD, False)]):
        write_episode(tmp_path / f"ep{i}.mcap", _episode(rng, opening, success, 0, "1.0"))
    model = instantiate(REFLECTOR).eval()
    encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
    paths = sorted(tmp_path.glob("ep*.mcap"))
    always = failure_modes(paths, judge=(model, encoder, 0.0, "agentview", 8))
    never = failure_modes(paths, judge=(model, encoder, 1.0, "agentview", 8))
    assert always["reflector_says_success"] == {"success": 1.0, "lost object": 1.0}
    assert never["reflector_says_success"] == {"success": 0.0, "lost object": 0.0}
    assert "| the success model says success | | 100% | - | 100% | - |" in table(always)


@pytest.mark.sim
def test_a_failure_that_sets_the_bowl_down_off_the_plates_centre_is_counted_apart(tmp_path):
    """The last recorded state, put back in the real simulator, says where the bowl ended (libero_spatial 0)."""
    from tests.worldenv_core.envs.test_goals import set_down
    from worldenv_core.data.mcap_io import write_episode
    from worldenv_core.envs.libero_env import LiberoEnv

    env = LiberoEnv("libero_spatial", 0, cameras=(), render=False)
    ends = {}
    env.reset(0)
    for name, dx in (("untouched", None), ("centre", 0.01), ("off", 0.05)):
        if dx is not None:
            set_down(env, "akita_black_bowl_1", "plate_1", dx)
        ends[name] = env.raw.get_sim_state().astype(np.float64)
    env.close()
    rng = np.random.default_rng(0)
    for i, (end, success) in enumerate((("centre", True), ("off", False), ("untouched", False))):
        ep = _episode(rng, EMPTY_THEN_HELD, success, 0, "1.0")
        ep.meta.suite, ep.meta.init_state_index = "libero_spatial", 0
        ep.sim_state = np.repeat(ends[end][None], len(EMPTY_THEN_HELD), axis=0)
        write_episode(tmp_path / f"ep{i}.mcap", ep)
    modes = failure_modes(sorted(tmp_path.glob("ep*.mcap")), final_state=True)
    assert modes["counts"] == {"success": 1, "placed off-centre": 1, "lost object": 1}
    assert modes["median_offset_m"] == {"success": pytest.approx(0.01, abs=0.005),
                                        "placed off-centre": pytest.approx(0.05, abs=0.005)}
    assert "placed off-centre" in table(modes) and "placed off-centre" not in table(failure_modes([tmp_path / "ep0.mcap"]))
