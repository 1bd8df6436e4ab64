import json

import numpy as np
import pytest

from analysis.budget import gains_by_budget, main
from tests.stages.test_suites import _kept_evaluation
from worldenv_core.errors import ConfigError

KEYS = [(t, i) for t in range(2) for i in range(50)]


def outcomes(successes):
    return {k: bool(s) for k, s in zip(KEYS, successes)}


def moved(start, gained, lost=0):
    """The start with its first `gained` failures solved and its first `lost` successes failed."""
    out = dict(start)
    out.update({k: True for k in [k for k, v in start.items() if not v][:gained]})
    out.update({k: False for k in [k for k, v in start.items() if v][:lost]})
    return out


def test_each_policy_gets_its_paired_gain_interval_and_mcnemar_against_the_start():
    start = outcomes([i % 2 == 0 for i in range(100)])
    result = gains_by_budget(start, [("real", 320, moved(start, 2, 1)), ("real", 1280, moved(start, 20)),
                                     ("imagined", 250, start)])
    assert result["episodes"] == 100 and result["start"] == 0.5
    small, large, same = result["policies"]
    assert (small["only_start"], small["only_it"], small["gain"]) == (1, 2, pytest.approx(0.01))
    assert small["gain_ci"][0] < 0 < small["gain_ci"][1] and small["p_value"] == 1.0
    assert large["gain"] == pytest.approx(0.2) and large["p_value"] < 1e-5 and large["gain_ci"][0] > 0.1
    assert large["real_episodes"] == 1280 and large["success"] == pytest.approx(0.7)
    assert same["gain"] == 0 and same["gain_ci"] == [0, 0] and same["p_value"] == 1.0


def test_per_task_success_shows_a_gain_on_one_task_paid_for_by_another():
    start = outcomes([i % 2 == 0 for i in range(100)])  # 25 of 50 on each task
    traded = dict(start)
    traded.update({k: True for k in KEYS if k[0] == 0})  # task 0 all solved, task 1 none: the same pooled rate
    traded.update({k: False for k in KEYS if k[0] == 1})
    result = gains_by_budget(start, [("real", 320, traded)])
    assert result["start_per_task"] == {0: 0.5, 1: 0.5}
    assert result["policies"][0]["per_task"] == {0: 1.0, 1: 0.0} and result["policies"][0]["gain"] == 0


def test_only_the_episodes_every_policy_and_the_start_ran_count():
    start = outcomes([1] * 100)
    half = {k: v for k, v in outcomes([0] * 100).items() if k[0] == 0}
    result = gains_by_budget(start, [("a", 0, half), ("b", 5, outcomes([1] * 100))])
    assert result["episodes"] == 50 and result["policies"][0]["gain"] == -1.0
    with pytest.raises(ConfigError, match="share no episode"):
        gains_by_budget(start, [("a", 0, {(9, 9): True})])
    with pytest.raises(ConfigError, match="negative"):
        gains_by_budget(start, [("a", -1, start)])
    with pytest.raises(ConfigError, match="at least one"):
        gains_by_budget(start, [])


def test_cli_pools_folders_writes_json_and_plot_and_names_bad_policies(tmp_path, capsys):
    s = tmp_path / "s"
    start = outcomes([i % 2 == 0 for i in range(100)])
    _kept_evaluation(tmp_path, "s", "evaluate-s0", "sft", "oracle", {k: v for k, v in start.items() if k[0] == 0})
    _kept_evaluation(tmp_path, "s", "evaluate-s1", "sft", "oracle", {k: v for k, v in start.items() if k[0] == 1})
    for name, gained in (("r10", 3), ("r40", 15), ("i0", 1), ("i1", 4)):
        _kept_evaluation(tmp_path, "s", f"evaluate-{name}", name, "oracle", moved(start, gained))
    result = main(["-", "--start", str(s / "evaluate-s0"), str(s / "evaluate-s1"),
                   "--policy", "real", "320", str(s / "evaluate-r10"), "--policy", "real", "1280", str(s / "evaluate-r40"),
                   "--policy", "imagined", "250", str(s / "evaluate-i0"), "--policy", "imagined", "250", str(s / "evaluate-i1"),
                   "--json", str(tmp_path / "budget.json"), "--plot", str(tmp_path / "budget.png"),
                   "--tasks-plot", str(tmp_path / "tasks.png")])
    assert [r["real_episodes"] for r in result["policies"]] == [320, 1280, 250, 250]
    assert np.allclose([r["gain"] for r in result["policies"]], [0.03, 0.15, 0.01, 0.04])
    assert json.loads((tmp_path / "budget.json").read_text())["policies"][1]["p_value"] == result["policies"][1]["p_value"]
    assert (tmp_path / "budget.png").stat().st_size > 0 and (tmp_path / "tasks.png").stat().st_size > 0
    assert result["policies"][1]["per_task"][0] > result["start_per_task"][0]  # the 15 solved are task 0's failures
    out = capsys.readouterr().out
    assert "| real | 1280 | 65.0 % | +15.0 [" in out and "the start solves 50.0 %" in out
    with pytest.raises(ConfigError, match="whole number"):
        main(["-", "--start", str(s / "evaluate-s0"), "--policy", "real", "many", str(s / "evaluate-r10")])
    with pytest.raises(ConfigError, match="at least one evaluation"):
        main(["-", "--start", str(s / "evaluate-s0"), "--policy", "real", "320"])
