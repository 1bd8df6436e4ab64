"""`python -m analysis.paired`: two policies' kept evaluations, pooled per side and paired by
(task, init state), with the exact McNemar test."""
import json

import pytest

from analysis.paired import main
from tests.stages.test_suites import _kept_evaluation
from worldenv_core.errors import ConfigError

KEYS = [(t, i) for t in range(2) for i in range(50)]


def test_each_sides_ranges_pool_and_a_small_p_is_printed_not_rounded_to_zero(tmp_path, capsys):
    """The start in two ranges of init states against a policy that solves 30 more episodes and
    loses none: p = 2 * 0.5 ** 30, which four decimals would have printed as 0.0000."""
    start = {k: k[1] >= 30 for k in KEYS}                  # 40 of 100 solved
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-s0", "ckpt/sft", "oracle",
                     {k: v for k, v in start.items() if k[1] < 20})
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-s1", "ckpt/sft", "oracle",
                     {k: v for k, v in start.items() if k[1] >= 20})
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-m", "ckpt/moved", "oracle",
                     {k: v or k[1] >= 15 for k, v in start.items()})  # 30 more: init states 15-29 of both tasks
    s = tmp_path / "libero_spatial"
    result = main(["-", "--a", str(s / "evaluate-s0"), str(s / "evaluate-s1"), "--b", str(s / "evaluate-m"),
                   "--json", str(tmp_path / "paired.json")])
    assert result["episodes"] == 100 and (result["only_a"], result["only_b"]) == (0, 30)
    assert result["a"] == pytest.approx(0.4) and result["b"] == pytest.approx(0.7)
    assert result["p_value"] == pytest.approx(2 * 0.5 ** 30)
    assert [t["only_b"] for t in result["per_task"]] == [15, 15]
    out = capsys.readouterr().out
    assert "exact McNemar p = 1.86e-09 over 100 paired episodes" in out and "0.0000" not in out
    assert json.loads((tmp_path / "paired.json").read_text())["only_b"] == 30


def test_sides_that_are_not_the_same_episodes_are_refused(tmp_path):
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-o", "ckpt/sft", "oracle", {(0, 0): True})
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-f", "ckpt/moved", "fixed", {(0, 0): True})
    _kept_evaluation(tmp_path, "libero_spatial", "evaluate-x", "ckpt/other", "oracle", {(0, 1): True})
    s = tmp_path / "libero_spatial"
    with pytest.raises(ConfigError, match="termination 'oracle' and 'fixed'"):
        main(["-", "--a", str(s / "evaluate-o"), "--b", str(s / "evaluate-f")])
    with pytest.raises(ConfigError, match="other weights"):     # one side pools two policies
        main(["-", "--a", str(s / "evaluate-o"), str(s / "evaluate-x"), "--b", str(s / "evaluate-f")])
    with pytest.raises(ConfigError, match="share no episode"):
        main(["-", "--a", str(s / "evaluate-o"), "--b", str(s / "evaluate-x")])
