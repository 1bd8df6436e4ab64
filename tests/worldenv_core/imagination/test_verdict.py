"""Verdict fidelity's imagination side and its metrics: `imagine` watches each rollout to the
horizon and keeps the actions it executed (so the real simulator can replay them) and its scores;
`judge` reads the verdict at any eta off them, exactly as the imagined env at that eta would
stop; the metrics score imagined verdicts against known real outcomes."""
import math

import numpy as np
import pytest
import torch

from tests.worldenv_core.imagination.test_recording import tiny_policy
from worldenv_core.imagination.verdict import (evaluator_metrics, frame_metrics, imagine, judge, pair, per_task,
                                               replay_eta, terminal_reward, verdict_metrics)
from worldenv_core.stats import spearman
from worldenv_core.rl.loop import collect_rollouts


def encoder(texts):
    return torch.stack([torch.full((16,), float(len(t))) for t in texts])


@pytest.mark.parametrize("eta", [0.0, 0.45, 0.5, 0.55, 1.0])
def test_verdicts_read_off_a_watched_rollout_equal_running_with_the_threshold(make_env, contexts, eta):
    """imagine() watches every rollout to the horizon; judge() cuts it at the first check with
    R > eta. That must be exactly what the imagined env at eta does (LOOP's rollouts)."""
    ctx = contexts()
    runs = imagine(tiny_policy(), make_env(0.5, horizon=12), ctx, 2, encoder, torch.Generator().manual_seed(0),
                   keep_steps=(4, 8), full_rollouts=(1,))
    assert [r.context for r in runs] == [0, 0, 1, 1, 2, 2]
    batch = collect_rollouts(tiny_policy(), make_env(eta, horizon=12), ctx, 2, encoder,
                             generator=torch.Generator().manual_seed(0))
    rows = [pair(r, {"scores": r.scores, "first_success": None, "error": None}, 0, "init", "p", chunk=4) for r in runs]
    judged = [judge(row, eta) for row in rows]
    assert [j["imagined_steps"] for j in judged] == batch.t_end.tolist()
    assert [j["imagined_success"] for j in judged] == batch.by_reflector.tolist()
    assert np.allclose([j["imagined_reward"] for j in judged], batch.rewards.tolist(), atol=1e-4)
    for i, r in enumerate(runs):
        assert r.steps == 12 and r.actions.shape == (12, 7) and r.actions.dtype == np.float32 and len(r.scores) == 4
        assert set(r.frames) == ({0, 4, 8, 12} if i == 1 else {4, 8})
        assert all(f.shape == (32, 32, 3) and f.dtype == np.uint8 for f in r.frames.values())
    # the executed actions are LOOP's sampled ones, in simulator units
    unnorm = tiny_policy().unnormalize_actions(batch.actions[0].flatten(0, 1)).numpy()
    stop = int(batch.t_end[0])
    assert np.allclose(runs[0].actions[:stop], unnorm[:stop], atol=1e-6)


def _row(imagined_scores, first, real_scores=None, context=0, task=0):
    return {"task_id": task, "context": context, "context_kind": "init", "chunk": 8, "steps": 32,
            "imagined_scores": imagined_scores, "real_scores": real_scores or [0.0] * len(imagined_scores),
            "real_first_success": first, "real_error": None}


def test_judge_stops_at_the_first_check_above_eta_and_asks_reality_by_then():
    row = _row([0.9, 0.2, 0.6, 0.8, 0.3], first=20, real_scores=[0.0, 0.1, 0.7, 0.9, 0.9])
    at_half = judge(row, 0.5)  # the score at step 0 never stops a rollout; 0.6 after chunk 2 does
    assert at_half["imagined_success"] and at_half["imagined_steps"] == 16 and at_half["imagined_reward"] == 0.6
    assert not at_half["real_success"] and at_half["real_reward"] == 0.7  # the oracle fires at 20, after the stop
    later = judge(row, 0.7)
    assert later["imagined_steps"] == 24 and later["real_success"]
    never = judge(row, 0.95)
    assert not never["imagined_success"] and never["imagined_steps"] == 32 and never["real_success"]


def test_verdict_metrics_count_hacks_misses_and_timing():
    rows = [_row([0, 0.1, 0.9], first=8, real_scores=[0, 0.1, 0.8]),  # agreed success, stop 16, 8 steps late
            _row([0, 0.7, 0.7], first=None, real_scores=[0, 0.1, 0.1]),  # a hack: imagined success, real failure
            _row([0, 0.1, 0.2], first=12, real_scores=[0, 0.1, 0.9]),  # missed
            _row([0, 0.1, 0.1], first=None), _row([0, 0.05, 0.05], first=None)]
    m = verdict_metrics(rows, eta=0.5, intervals=True)
    assert m["rollouts"] == 5 and m["hacks"] == 1 and m["missed"] == 1
    assert m["hack_rate"] == 0.5 and m["precision"] == 0.5 and m["recall"] == 0.5 and m["f1"] == 0.5
    assert m["imagined_success"] == 0.4 and m["real_success"] == 0.4 and m["success_gap"] == 0.0
    assert m["timing_error_median"] == 8
    assert m["auroc"] == pytest.approx(5 / 6)  # real successes score 0.9 and 0.2 against 0.7, 0.1, 0.05
    assert m["real_frames_f1"] == 1.0  # the reflector on the real frames gets all of them right
    assert m["real_stop_f1"] == 1.0 and m["real_stop_auroc"] == 1.0
    assert per_task(rows, 0.5) == {0: {"rollouts": 5, "imagined_success": 0.4, "real_success": 0.4}}
    assert verdict_metrics([], 0.5) == {"rollouts": 0}
    assert m["auroc_ci95"] == [m["auroc"]] * 2  # one context: nothing to resample
    for i, r in enumerate(rows):
        r["context"] = i
    m = verdict_metrics(rows, eta=0.5, intervals=True)
    low, high = m["auroc_ci95"]
    assert low <= m["auroc"] <= high and 0 <= low < high <= 1  # five contexts of one rollout each: wide
    assert m["f1_ci95"][0] <= m["f1"] <= m["f1_ci95"][1]
    assert m["hack_rate_ci95"][0] <= m["hack_rate"] <= m["hack_rate_ci95"][1]  # 1 of 2 imagined successes
    assert 0 <= m["hack_rate_ci95"][0] < m["hack_rate_ci95"][1] <= 1


def test_mixed_groups_count_the_contexts_whose_rollouts_disagree_imagined_and_real():
    """LOOP's learning signal: groups (rollouts of one context) whose verdicts are not all the same."""
    rows = [_row([0, 0.9], first=8), _row([0, 0.1], first=8),  # context 0: imagination splits, reality agrees
            _row([0, 0.1], first=None), _row([0, 0.2], first=4),  # context 1: imagination agrees, reality splits
            _row([0, 0.1], first=None), _row([0, 0.1], first=None)]  # context 2: both agree
    for i, r in enumerate(rows):
        r["context"] = i // 2
    m = verdict_metrics(rows, eta=0.5)
    assert m["imagined_mixed_groups"] == pytest.approx(1 / 3) and m["real_mixed_groups"] == pytest.approx(1 / 3)
    # pairs kept before a benchmark init state's start named its task: 'init0' of three tasks, three groups
    for i, r in enumerate(rows):
        r.update(context_kind="init", start="init0", task_id=i // 2)
    m = verdict_metrics(rows, eta=0.5)
    assert m["imagined_mixed_groups"] == pytest.approx(1 / 3) and m["real_mixed_groups"] == pytest.approx(1 / 3)
    for i, r in enumerate(rows):
        r["context"], r["start"] = i, f"task{i // 2}/init{i}"  # one rollout per context: no group to disagree
    assert "real_mixed_groups" not in verdict_metrics(rows, eta=0.5)


def test_the_reflector_terminating_real_replays_sees_a_success_the_horizon_no_longer_shows():
    # the open-loop actions pass through success at step 10 and go on: the last real frame shows
    # no success, the one after the second chunk did; imagination never stopped
    rows = [_row([0, 0.1, 0.1, 0.1, 0.1], first=10, real_scores=[0, 0.1, 0.9, 0.3, 0.2]),
            _row([0, 0.1, 0.1, 0.1, 0.1], first=None, real_scores=[0, 0.1, 0.2, 0.3, 0.2])]
    m = verdict_metrics(rows, eta=0.5)
    assert m["real_frames_recall"] == 0.0  # asked at the horizon, where imagination was cut
    assert m["real_stop_recall"] == 1.0 and m["real_stop_precision"] == 1.0 and m["real_stop_auroc"] == 1.0


def test_eta_chosen_on_replays_is_judged_on_the_other_contexts():
    # real successes score 0.3 in imagination, failures 0.1: the paper's 0.5 misses them all; of the
    # etas that separate them on the other half, the one closest to 0.5 is chosen
    rows = [_row([0, s, s], first=4 if ok else None, context=c) for c in range(4) for s, ok in ((0.3, True), (0.1, False))]
    assert verdict_metrics(rows, 0.5)["f1"] == 0.0
    out = replay_eta(rows)
    assert out["folds"] == 2 and out["etas"] == [0.25, 0.25] and out["f1"] == 1.0
    assert out["hack_rate"] == 0.0 and out["rollouts"] == 8
    assert replay_eta(rows[:2]) == {"folds": 2, "etas": []}  # one context: nothing to hold out
    # every other context (their numbers all even, as the 1/3 frames of two-frame demos are): folds still split them
    evens = [r for r in rows if r["context"] % 2 == 0]
    assert replay_eta(evens)["etas"] == [0.25, 0.25] and replay_eta(evens)["rollouts"] == 4


def test_frame_metrics_pair_frames_by_step_and_skip_the_shared_start():
    rng = np.random.default_rng(0)
    real = {s: rng.integers(0, 255, (16, 16, 3), dtype=np.uint8) for s in (0, 8, 16)}
    same = frame_metrics(dict(real), real)
    assert set(same) == {8, 16} and all(math.isinf(p) or p > 60 for p, _ in same.values())
    assert all(s == pytest.approx(1.0) for _, s in same.values())
    noisy = {s: np.clip(f.astype(int) + 40, 0, 255).astype(np.uint8) for s, f in real.items() if s != 16}
    worse = frame_metrics(noisy, real)
    assert set(worse) == {8} and worse[8][0] < 30


def test_the_policy_evaluator_ranks_policies():
    per_policy = {"a": {"imagined_success": 0.1, "closed_loop_success": 0.2},
                  "b": {"imagined_success": 0.3, "closed_loop_success": 0.4},
                  "c": {"imagined_success": 0.6, "closed_loop_success": 0.5},
                  "d": {"imagined_success": 0.5, "closed_loop_success": None}}
    m = evaluator_metrics(per_policy)
    assert m["policies"] == 3 and m["spearman"] == pytest.approx(1.0) and m["mae"] == pytest.approx(0.1)
    assert math.isnan(evaluator_metrics({"a": per_policy["a"]})["spearman"])
    # no imagined rollout reached eta: success says nothing, the mean imagined reward still ranks them
    rewards = {n: {**m, "imagined_success": 0.0, "imagined_reward": m["imagined_success"] / 2} for n, m in per_policy.items()}
    assert math.isnan(evaluator_metrics(rewards)["spearman"])
    assert evaluator_metrics(rewards, imagined_key="imagined_reward")["spearman"] == pytest.approx(1.0)
    assert terminal_reward([0.9, 0.2, 0.6, 0.8], 0.5) == 0.6 and terminal_reward([0.9, 0.2, 0.3], 0.5) == 0.3
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert spearman([1, 1, 2], [1, 2, 3]) == pytest.approx(math.sqrt(3) / 2)  # ties share their mean rank
    assert math.isnan(spearman([1, 1, 1], [1, 2, 3]))
