"""Stored pairs as reflector training data: labels from the real outcome at each check, both
sides, refusals where an evaluation judges, and the prefix sampler reading check-only episodes."""
import json

import numpy as np
import pytest

from worldenv_core.imagination.pairs import (calibration_rows, calibration_starts, checked_episodes, eta_on_pairs,
                                             store_pair_frames)
from worldenv_core.models.reflector_data import PrefixSampler

EPISODE = "/data/tiny/expert-0/task00/expert_0001.mcap"


def write_pairs(folder, rows, checks=5):
    """A work dir as evaluate_imagination leaves it: a variant's rows and its frames (imagined frame k
    filled with k, real with 100 + k, so a test can tell which frame went where)."""
    (folder / "ab12.json").write_text(json.dumps({"rows": rows}))
    (folder / "fidelity.json").write_text("{}")
    for i, _ in enumerate(rows):
        frames = {k * 8: np.full((4, 4, 3), k, np.uint8) for k in range(checks)}
        real = {k * 8: np.full((4, 4, 3), 100 + k, np.uint8) for k in range(checks)}
        store_pair_frames(folder / "frames" / "ab12" / f"{i:04d}.npz", frames, real)


def row(first_success, kind="episode", start=f"{EPISODE}@12", error=None):
    return {"task_id": 0, "context_kind": kind, "chunk": 8, "steps": 32, "start": start,
            "real_first_success": first_success, "real_error": error}


def test_each_check_is_labelled_by_whether_the_real_replay_had_succeeded_by_then(tmp_path):
    write_pairs(tmp_path, [row(13), row(None), row(5, error="replay failed")])
    eps = checked_episodes(tmp_path, {0: "open the drawer"}, forbidden=set())
    assert [ep.meta.side for ep in eps] == ["imagined", "real", "imagined", "real"]  # the failed replay skipped
    assert eps[0].success.tolist() == [False, False, True, True, True]  # checks at steps 0, 8, 16, 24, 32
    assert eps[1].success.tolist() == eps[0].success.tolist() and not eps[2].success.any()
    assert eps[0].video().shape == (5, 3, 4, 4) and int(eps[1].frames[3, 0, 0, 0]) == 103
    assert eps[0].steps_per_frame == 8 and eps[0].meta.instruction == "open the drawer"


def test_a_keyframes_recorded_past_goes_before_both_sides_as_checks_not_yet_succeeded(tmp_path):
    import torch

    write_pairs(tmp_path, [row(13)])
    past = torch.full((2, 3, 4, 4), 200, dtype=torch.uint8)
    eps = checked_episodes(tmp_path, {0: "x"}, forbidden=set(), past_of=lambda r: past)
    for ep in eps:  # two recorded checks, then the pair's five
        assert ep.success.tolist() == [False] * 2 + [False, False, True, True, True]
        assert ep.frames.shape == (7, 4, 4, 3) and int(ep.frames[1, 0, 0, 0]) == 200
    assert int(eps[0].frames[2, 0, 0, 0]) == 0 and int(eps[1].frames[2, 0, 0, 0]) == 100


def test_pairs_that_start_where_evaluations_judge_are_refused(tmp_path):
    write_pairs(tmp_path, [row(None, kind="init", start="task0@init0")])
    with pytest.raises(ValueError, match="benchmark init state"):
        checked_episodes(tmp_path, {0: "x"}, forbidden=set())
    write_pairs(tmp_path, [row(None)])
    with pytest.raises(ValueError, match="expert_0001"):
        checked_episodes(tmp_path, {0: "x"}, forbidden={"expert-0/task00/expert_0001.mcap"})
    with pytest.raises(FileNotFoundError, match="no stored pairs"):
        checked_episodes(tmp_path / "frames", {0: "x"}, forbidden=set())


def test_the_sampler_counts_stride_delay_and_hard_window_in_a_check_only_episodes_own_frames(tmp_path):
    write_pairs(tmp_path, [row(13)], checks=9)  # success by check 2 (step 16)
    eps = checked_episodes(tmp_path, {0: "x"}, forbidden=set())
    sampler = PrefixSampler(eps, "agentview", stride=8, max_frames=32, hard_window=16, label_delay=8)
    assert sampler.strides == [1, 1]
    assert sampler.labels[0].tolist() == [False] * 3 + [True] * 6  # the settled label: one check (8 steps) later
    assert {tuple(x) for x in sampler.hard} == {(i, t) for i in (0, 1) for t in (1, 2)}  # 16 steps = 2 checks
    batch = sampler.gather(np.array([[0, 4]]))
    assert batch["mask"].sum() == 5 and batch["frames"][0, :5, 0, 0, 0].tolist() == [0, 1, 2, 3, 4]  # every check


def test_pairs_set_aside_choose_eta_by_the_verdicts_f1_and_are_not_trained_on(tmp_path):
    starts = [f"/data/tiny/expert-0/task00/expert_000{i}.mcap@12" for i in range(4)]
    # two real successes (by step 13) and two failures, one start episode each
    write_pairs(tmp_path, [row(13, start=starts[0]), row(13, start=starts[1]), row(None, start=starts[2]),
                           row(None, start=starts[3])])
    aside = calibration_starts([tmp_path], 2)
    assert aside == {"expert-0/task00/expert_0001.mcap", "expert-0/task00/expert_0003.mcap"}  # every 2nd, key order
    assert calibration_starts([tmp_path], 0) == set()
    trained = checked_episodes(tmp_path, {0: "x"}, forbidden=set(), set_aside=aside)
    assert {ep.meta.start for ep in trained} == {starts[0], starts[2]}
    held = [({**r, "real_scores": [0.0] * 5}, path) for r, path in calibration_rows([tmp_path], aside)]
    assert [r["start"] for r, _ in held] == [starts[1], starts[3]]
    # a scorer whose R reaches 0.7 on the real success (after it) and 0.4 on the failure: only an eta in
    # [0.4, 0.7) stops the one and not the other; ties go to the eta closest to the prior
    peak = {starts[1]: 0.7, starts[3]: 0.4}
    score = lambda r, frames: [0.0, 0.0] + [peak[r["start"]]] * (len(frames) - 2)  # noqa: E731 (from step 16 on)
    out = eta_on_pairs(held, score, grid=(0.3, 0.5, 0.65, 0.8), prior=0.5)
    assert out["pairs"] == 2 and out["chosen_eta"] == 0.5 and out["at_chosen"]["f1"] == 1.0
    assert out["eta_sweep"]["0.3"]["hack_rate"] == 0.5 and out["eta_sweep"]["0.8"]["imagined_success"] == 0.0
