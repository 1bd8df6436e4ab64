"""Stored pairs as reflector training data: labels from the real outcome at each check, both
sides, refusals where an evaluation judges, and the prefix sampler reading check-only episodes."""
import json

import numpy as np
import pytest

from worldenv_core.imagination.pairs import checked_episodes, store_pair_frames
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
