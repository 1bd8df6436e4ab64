import json
import math

import numpy as np
import pytest

from analysis.seeds import compare_procedures, main
from tests.stages.test_suites import _kept_evaluation
from worldenv_core.errors import ConfigError

KEYS = [(t, i) for t in range(2) for i in range(50)]


def outcomes(successes):
    return {k: bool(s) for k, s in zip(KEYS, successes)}


def test_seeds_that_each_beat_the_start_are_no_better_than_the_other_procedures_seeds():
    """Each seed's McNemar test against the start can be significant while the procedures do not
    differ: the test counts the policies, not the episodes."""
    rng = np.random.default_rng(0)
    start = outcomes(rng.random(100) < 0.5)
    def moved(gain):  # the start with `gain` failures turned into successes
        out, failed = dict(start), [k for k, v in start.items() if not v]
        out.update({k: True for k in failed[:gain]})
        return out
    result = compare_procedures({"method": [moved(12), moved(1)], "random": [moved(11), moved(2)]}, start)
    method = result["procedures"]["method"]
    assert result["episodes"] == 100 and result["start"] == pytest.approx(np.mean(list(start.values())))
    assert [r["only_it"] for r in method["policies"]] == [12, 1] and method["policies"][0]["p_value"] < 0.001
    assert method["policies"][0]["gain"] == pytest.approx(0.12)
    assert result["difference"] == pytest.approx(0.0) and result["permutation_p"] == 1.0
    assert result["relabellings"] == math.comb(4, 2)


def test_only_the_episodes_every_policy_ran_count_and_two_procedures_are_required():
    half = {k: v for k, v in outcomes([1] * 100).items() if k[0] == 0}
    result = compare_procedures({"a": [outcomes([1] * 100)], "b": [half, outcomes([0] * 100)]})
    assert result["episodes"] == 50 and result["start"] is None
    with pytest.raises(ConfigError, match="exactly two"):
        compare_procedures({"a": [half]})
    with pytest.raises(ConfigError, match="share no episode"):
        compare_procedures({"a": [{(9, 9): True}], "b": [half]})


def test_cli_pools_each_policys_folders_writes_json_and_plot(tmp_path, capsys):
    s = tmp_path / "s"
    start = outcomes([i % 2 == 0 for i in range(100)])
    _kept_evaluation(tmp_path, "s", "evaluate-s0", "sft", "oracle", {k: v for k, v in start.items() if k[0] == 0})
    _kept_evaluation(tmp_path, "s", "evaluate-s1", "sft", "oracle", {k: v for k, v in start.items() if k[0] == 1})
    for name, rate in (("m0", 3), ("m1", 4), ("r0", 2), ("r1", 5)):
        _kept_evaluation(tmp_path, "s", f"evaluate-{name}", name, "oracle", outcomes([i % rate != 1 for i in range(100)]))
    result = main(["-", "--start", str(s / "evaluate-s0"), str(s / "evaluate-s1"),
                   "--policy", "loop", str(s / "evaluate-m0"), "--policy", "loop", str(s / "evaluate-m1"),
                   "--policy", "random", str(s / "evaluate-r0"), "--policy", "random", str(s / "evaluate-r1"),
                   "--json", str(tmp_path / "seeds.json"), "--plot", str(tmp_path / "seeds.png")])
    assert list(result["procedures"]) == ["loop", "random"] and result["start"] == 0.5
    assert json.loads((tmp_path / "seeds.json").read_text())["permutation_p"] == result["permutation_p"]
    assert (tmp_path / "seeds.png").stat().st_size > 0
    assert "exact permutation p" in capsys.readouterr().out
    _kept_evaluation(tmp_path, "s", "evaluate-f", "fixed", "fixed", outcomes([1] * 100))
    with pytest.raises(ConfigError, match="different terminations"):
        main(["-", "--policy", "a", str(s / "evaluate-m0"), "--policy", "b", str(s / "evaluate-f")])
    with pytest.raises(ConfigError, match="name followed"):
        main(["-", "--policy", "a"])
