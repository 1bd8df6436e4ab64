"""Verdict fidelity's imagination side and its metrics: `imagine` keeps exactly the actions each
rollout executed (so the real simulator can replay them) with its verdict; the metrics score the
imagined verdict against known real outcomes."""
import math

import numpy as np
import pytest
import torch

from tests.worldenv_core.imagination.test_recording import tiny_policy
from worldenv_core.imagination.verdict import evaluator_metrics, frame_metrics, imagine, pair, per_task, verdict_metrics
from worldenv_core.metrics import spearman
from worldenv_core.rl.loop import collect_rollouts


def encoder(texts):
    return torch.stack([torch.full((16,), float(len(t))) for t in texts])


@pytest.mark.parametrize("eta", [1.0, 0.0])  # 1.0: every rollout runs to the horizon; 0.0: each stops at once
def test_imagine_keeps_the_executed_actions_and_the_verdict_of_each_rollout(make_env, contexts, eta):
    env, ctx = make_env(eta, horizon=12), contexts()
    runs = imagine(tiny_policy(), env, ctx, 2, encoder, torch.Generator().manual_seed(0), keep_steps=(4, 8),
                   full_rollouts=(1,))
    assert [r.context for r in runs] == [0, 0, 1, 1, 2, 2]
    # the same draw as LOOP's own rollouts: the same generator gives the same verdicts and rewards
    batch = collect_rollouts(tiny_policy(), make_env(eta, horizon=12), ctx, 2, encoder,
                             generator=torch.Generator().manual_seed(0))
    assert [r.steps for r in runs] == batch.t_end.tolist()
    assert [r.success for r in runs] == batch.by_reflector.tolist()
    assert np.allclose([r.reward for r in runs], batch.rewards.tolist())
    for i, r in enumerate(runs):
        assert r.actions.shape == (r.steps, 7) and r.actions.dtype == np.float32  # what was executed, nothing after
        expected = {0, 4, 8, 12} if i == 1 else {4, 8}
        assert set(r.frames) == {s for s in expected if s <= r.steps}
        assert all(f.shape == (32, 32, 3) and f.dtype == np.uint8 for f in r.frames.values())
    if eta == 1.0:
        assert all(r.steps == 12 and not r.success for r in runs)
    # the executed actions are LOOP's sampled ones, in simulator units
    unnorm = tiny_policy().unnormalize_actions(batch.actions[0].flatten(0, 1)).numpy()
    assert np.allclose(runs[0].actions, unnorm[:runs[0].steps], atol=1e-6)


def _row(imagined, reward, real, steps=40, first=30, real_reward=0.0):
    return {"task_id": 0, "context_kind": "init", "imagined_success": imagined, "imagined_reward": reward,
            "imagined_steps": steps, "real_success": real, "real_first_success": first if real else None,
            "real_reward": real_reward}


def test_verdict_metrics_count_hacks_misses_and_timing():
    rows = [_row(True, 0.9, True, steps=40, first=32, real_reward=0.8),  # agreed success, 8 steps late
            _row(True, 0.7, False, real_reward=0.1),  # a hack: imagined success, real failure
            _row(False, 0.2, True, real_reward=0.9),  # missed
            _row(False, 0.1, False), _row(False, 0.05, False)]
    m = verdict_metrics(rows, eta=0.5)
    assert m["rollouts"] == 5 and m["hacks"] == 1 and m["missed"] == 1
    assert m["hack_rate"] == 0.5 and m["precision"] == 0.5 and m["recall"] == 0.5 and m["f1"] == 0.5
    assert m["imagined_success"] == 0.4 and m["real_success"] == 0.4 and m["success_gap"] == 0.0
    assert m["timing_error_median"] == 8
    assert m["auroc"] == pytest.approx(5 / 6)  # real successes score 0.9 and 0.2 against 0.7, 0.1, 0.05
    assert m["real_frames_f1"] == 1.0  # the reflector on the real frames gets all of them right
    assert per_task(rows) == {0: {"rollouts": 5, "imagined_success": 0.4, "real_success": 0.4}}
    assert verdict_metrics([], 0.5) == {"rollouts": 0}


def test_pair_joins_the_imagined_verdict_with_the_real_replay():
    from worldenv_core.imagination.verdict import ImaginedRun

    run = ImaginedRun(context=3, actions=np.zeros((16, 7), np.float32), success=True, reward=0.8, steps=16)
    real = {"success": False, "first_success": None, "success_at_end": False, "error": None, "scores": [0.1, 0.7, 0.3]}
    row = pair(run, real, eta=0.5, task_id=2, context_kind="episode", policy="sft@1")
    assert row["imagined_success"] and not row["real_success"] and row["real_reward"] == 0.3
    assert row["real_reflector_success"]  # the reflector would have stopped at 0.7 on the real frames


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
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert spearman([1, 1, 2], [1, 2, 3]) == pytest.approx(math.sqrt(3) / 2)  # ties share their mean rank
    assert math.isnan(spearman([1, 1, 1], [1, 2, 3]))
