import json
import math

import numpy as np
import pytest

from analysis.odd_one_out import main, odd_one_out, poisson_binomial
from tests.stages.test_suites import _kept_evaluation
from worldenv_core.errors import ConfigError


def test_poisson_binomial_is_the_binomial_when_the_probabilities_agree_and_sums_to_one():
    dist = poisson_binomial(np.full(7, 0.3))
    assert np.allclose(dist, [math.comb(7, j) * 0.3 ** j * 0.7 ** (7 - j) for j in range(8)])
    uneven = poisson_binomial(np.array([0.0, 1.0, 0.5, 0.25]))
    assert uneven.sum() == pytest.approx(1.0) and uneven[0] == 0.0 and uneven[4] == 0.0


def outcomes(successes):
    return {(t, i): bool(s) for (t, i), s in zip([(t, i) for t in range(2) for i in range(50)], successes)}


def test_a_start_that_alone_fails_where_its_updates_succeed_is_the_odd_one():
    shared, lost = np.random.default_rng(0).random(100) < 0.5, np.arange(100) < 20
    others = [outcomes(shared | lost) for _ in range(3)]  # 20 episodes only the start fails
    result = odd_one_out(outcomes(shared & ~lost), others)
    assert result["episodes"] == 100 and result["episodes_that_differ"] == 20
    assert result["alone_fails"] == [20, 0, 0, 0] and result["alone_succeeds"] == [0, 0, 0, 0]
    assert result["p_value"] < 1e-6 and result["first_successes"] < result["expected"]
    same = odd_one_out(others[0], others[1:])
    assert same["p_value"] == 1.0 and same["episodes_that_differ"] == 0


def test_only_the_episodes_every_policy_ran_count_and_none_shared_is_refused():
    a = outcomes([1] * 100)
    b = {k: v for k, v in outcomes([0] * 100).items() if k[0] == 0}
    assert odd_one_out(a, [b])["episodes"] == 50
    with pytest.raises(ConfigError, match="share no episode"):
        odd_one_out({(5, 0): True}, [b])
    with pytest.raises(ConfigError, match="at least one"):
        odd_one_out(a, [])


def test_cli_pools_kept_folders_and_refuses_other_terminations(tmp_path, capsys):
    first = outcomes([i % 3 == 0 for i in range(100)])
    _kept_evaluation(tmp_path, "s", "evaluate-a1", "sft", "oracle", {k: v for k, v in first.items() if k[0] == 0})
    _kept_evaluation(tmp_path, "s", "evaluate-a2", "sft", "oracle", {k: v for k, v in first.items() if k[0] == 1})
    _kept_evaluation(tmp_path, "s", "evaluate-b", "post", "oracle", outcomes([1] * 100))
    _kept_evaluation(tmp_path, "s", "evaluate-c", "control", "oracle", outcomes([i % 2 == 0 for i in range(100)]))
    folder = tmp_path / "s"
    result = main(["-", "--first", str(folder / "evaluate-a1"), str(folder / "evaluate-a2"),
                   "--other", str(folder / "evaluate-b"), "--other", str(folder / "evaluate-c"),
                   "--json", str(tmp_path / "odd.json")])
    assert result["episodes"] == 100 and result["policies"] == ["sft", "post", "control"]
    assert json.loads((tmp_path / "odd.json").read_text())["p_value"] == result["p_value"]
    assert "**sft** (first)" in capsys.readouterr().out
    _kept_evaluation(tmp_path, "s", "evaluate-d", "post", "fixed", outcomes([1] * 100))
    with pytest.raises(ConfigError, match="different terminations"):
        main(["-", "--first", str(folder / "evaluate-a1"), "--other", str(folder / "evaluate-d")])
