"""Reflector labels, stop decisions and termination/classification metrics, by hand."""
import math

import numpy as np

from worldenv_core.stats import auroc, binary_metrics
from worldenv_core.rl.termination import (StopOutcome, best_eta, check_steps, episode_outcomes, first_stop, first_success,
                                          success_labels, termination_metrics)


def test_labels_are_one_from_the_first_oracle_success_onward():
    flags = np.array([0, 0, 1, 0, 1, 0], dtype=bool)  # the oracle may flicker after success
    assert success_labels(flags).tolist() == [0, 0, 1, 1, 1, 1]
    assert first_success(flags) == 2 and first_success(np.zeros(4, bool)) is None


def test_check_steps_are_chunk_boundaries_plus_the_last_frame():
    assert check_steps(20, 8) == [0, 8, 16, 19]
    assert check_steps(17, 8) == [0, 8, 16]
    assert check_steps(1, 8) == [0]


def test_first_stop_is_the_first_check_strictly_above_eta():
    steps = [0, 8, 16, 24]
    assert first_stop(steps, [0.1, 0.5, 0.51, 0.9], 0.5) == 16
    assert first_stop(steps, [0.1, 0.2, 0.3, 0.4], 0.5) is None


def test_termination_metrics_by_hand():
    outcomes = [StopOutcome(10, 16),   # correct, 6 steps late
                StopOutcome(10, 10),   # correct, on time
                StopOutcome(20, 8),    # false stop before success
                StopOutcome(None, 40),  # false stop in a failure
                StopOutcome(30, None),  # missed success
                StopOutcome(None, None)]  # failure, never stopped: right
    assert [o.kind for o in outcomes] == ["correct", "correct", "false_stop", "false_stop", "missed", "no_stop"]
    m = termination_metrics(outcomes)
    assert (m["correct_stops"], m["false_stops"], m["missed_successes"], m["no_stop_failures"]) == (2, 2, 1, 1)
    assert m["false_stops_before_success"] == 1
    assert math.isclose(m["precision"], 0.5) and math.isclose(m["recall"], 2 / 3)
    assert math.isclose(m["f1"], 4 / 7)
    assert math.isclose(m["false_stop_before_success_rate"], 1 / 4)  # 4 successful episodes
    assert math.isclose(m["false_stop_in_failure_rate"], 1 / 2)  # 2 failed episodes
    assert math.isclose(m["missed_success_rate"], 1 / 4)
    assert m["timing_error_median"] == 3.0 and m["early_stop_error_mean"] == 12.0


def test_binary_metrics_and_auroc_by_hand():
    scores = [0.9, 0.8, 0.4, 0.3, 0.6, 0.1]
    labels = [1, 1, 1, 0, 0, 0]
    m = binary_metrics(scores, labels, 0.5)
    assert (m["tp"], m["fp"], m["fn"], m["tn"]) == (2, 1, 1, 2)
    assert math.isclose(m["accuracy"], 4 / 6) and math.isclose(m["f1"], 4 / 6)
    # pairs (pos, neg) ranked right: 0.9 and 0.8 beat all 3; 0.4 beats 0.3 and 0.1 -> 8 of 9
    assert math.isclose(m["auroc"], 8 / 9)
    assert math.isclose(auroc([0.5, 0.5], [1, 0]), 0.5)  # a tie counts half
    assert math.isnan(auroc([0.2, 0.3], [1, 1]))


def test_episode_outcomes_read_every_mode_off_one_rollout():
    flags = np.zeros(41, bool)
    flags[[20, 21, 22, 30]] = True  # success at 20, undone at 23, back at 30 only
    checks, scores = [0, 8, 16, 24, 32], [0.1, 0.2, 0.3, 0.7, 0.9]
    out = episode_outcomes(flags, checks, scores, eta=0.5)
    assert out["oracle"] == {"success": True, "steps": 20, "stop_step": None}
    assert out["fixed"] == {"success": False, "steps": 40, "stop_step": None}
    assert out["reflector"] == {"success": False, "steps": 24, "stop_step": 24}  # stopped after it was undone
    never = episode_outcomes(flags, checks, scores, eta=0.95)
    assert never["reflector"] == {"success": False, "steps": 40, "stop_step": None}
    early = episode_outcomes(flags, checks, scores, eta=0.25)
    assert early["reflector"] == {"success": False, "steps": 16, "stop_step": 16}
    assert episode_outcomes(np.zeros(5, bool), [], [], 0.5)["oracle"] == {"success": False, "steps": 4, "stop_step": None}


def test_best_eta_takes_the_highest_f1_and_breaks_ties_towards_the_configured_eta():
    assert best_eta({"0.3": 0.8, "0.5": 0.85, "0.8": 0.9, "0.9": 0.9}, prior=0.5) == 0.8
    assert best_eta({"0.3": 0.8, "0.5": 0.8, "0.7": 0.8}, prior=0.5) == 0.5  # a flat sweep keeps eta
    assert best_eta({"0.1": float("nan"), "0.2": 0.0}, prior=0.1) == 0.2  # NaN (nothing to stop) is worst
