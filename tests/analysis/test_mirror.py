import json

import pytest

from analysis.mirror import compare_directions, direction_and_size, main
from tests.analysis.test_budget import moved, outcomes
from tests.stages.test_suites import _kept_evaluation
from worldenv_core.errors import ConfigError


def test_a_gain_its_mirror_loses_is_the_directions_and_one_both_share_is_the_sizes():
    start = outcomes([i % 2 == 0 for i in range(100)])
    result = direction_and_size(start, [("pointed", moved(start, 12), moved(start, 0, 12)),
                                        ("curved", moved(start, 12), moved(start, 12)),
                                        ("still", start, start)])
    pointed, curved, still = result["moves"]
    assert result["episodes"] == 100 and result["start"] == 0.5
    assert pointed["move"]["gain"] == pytest.approx(0.12) and pointed["mirror"]["gain"] == pytest.approx(-0.12)
    assert pointed["direction"] == pytest.approx(0.12) and pointed["size"] == pytest.approx(0.0)
    assert (pointed["only_mirror"], pointed["only_move"]) == (0, 24) and pointed["direction_p"] < 1e-6
    assert pointed["direction_ci"][0] > 0.05 and pointed["size_ci"][0] < 0 < pointed["size_ci"][1]
    assert curved["direction"] == 0 and curved["direction_p"] == 1.0
    assert curved["size"] == pytest.approx(0.12) and curved["size_ci"][0] > 0 and curved["size_p"] < 1e-3
    assert pointed["size_p"] == pytest.approx(1.0)
    assert still["direction"] == still["size"] == 0 and still["size_p"] == 1.0


def test_only_episodes_every_side_ran_count_and_bad_input_is_named():
    start = outcomes([1] * 100)
    half = {k: v for k, v in outcomes([0] * 100).items() if k[0] == 0}
    assert direction_and_size(start, [("a", half, start)])["episodes"] == 50
    with pytest.raises(ConfigError, match="share no episode"):
        direction_and_size(start, [("a", {(9, 9): True}, start)])
    with pytest.raises(ConfigError, match="at least one"):
        direction_and_size(start, [])


def test_cli_pairs_each_move_with_its_mirror_and_writes_json_and_plot(tmp_path, capsys):
    s = tmp_path / "s"
    start = outcomes([i % 2 == 0 for i in range(100)])
    _kept_evaluation(tmp_path, "s", "evaluate-s", "sft", "oracle", start)
    for name, side in (("up", moved(start, 8)), ("down", moved(start, 0, 8)), ("r", moved(start, 4)),
                       ("rm", moved(start, 6))):
        _kept_evaluation(tmp_path, "s", f"evaluate-{name}", name, "oracle", side)
    result = main(["-", "--start", str(s / "evaluate-s"), "--move", "LOOP", str(s / "evaluate-up"),
                   "--mirror", str(s / "evaluate-down"), "--move", "random", str(s / "evaluate-r"),
                   "--mirror", str(s / "evaluate-rm"), "--json", str(tmp_path / "m.json"), "--plot", str(tmp_path / "m.png")])
    assert [r["label"] for r in result["moves"]] == ["LOOP", "random"]
    assert result["moves"][0]["direction"] == pytest.approx(0.08) and result["moves"][1]["size"] == pytest.approx(0.05)
    assert json.loads((tmp_path / "m.json").read_text())["moves"][0]["direction_p"] == result["moves"][0]["direction_p"]
    assert (tmp_path / "m.png").stat().st_size > 0
    assert "| LOOP | +8.0 [" in capsys.readouterr().out
    grouped = main(["-", "--start", str(s / "evaluate-s"), "--move", "LOOP", str(s / "evaluate-up"),
                    "--mirror", str(s / "evaluate-down"), "--move", "random", str(s / "evaluate-r"),
                    "--mirror", str(s / "evaluate-rm"), "--procedure", "RL", "1", "--procedure", "random", "2"])
    assert grouped["by_procedure"]["procedures"]["RL"]["up"] == 1 and grouped["by_procedure"]["permutation_p"] == 0.5
    assert "RL +8.0 on average, 1 of 1 up (sign test p 0.5)" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="give a name, then move numbers"):
        main(["-", "--start", str(s / "evaluate-s"), "--move", "LOOP", str(s / "evaluate-up"),
              "--mirror", str(s / "evaluate-down"), "--procedure", "RL", "first"])
    with pytest.raises(ConfigError, match="one mirror per move"):
        main(["-", "--start", str(s / "evaluate-s"), "--move", "LOOP", str(s / "evaluate-up"),
              "--move", "random", str(s / "evaluate-r"), "--mirror", str(s / "evaluate-down")])
    with pytest.raises(ConfigError, match="at least one evaluation"):
        main(["-", "--start", str(s / "evaluate-s"), "--move", "LOOP", "--mirror", str(s / "evaluate-down")])


def test_procedures_count_directions_pointing_up_and_test_one_against_the_other():
    result = {"moves": [{"label": f"m{i}", "direction": d} for i, d in enumerate([0.05, 0.03, 0.07, 0.04, -0.03])]}
    by = compare_directions(result, {"RL": [1, 2, 3], "random": [4, 5]})
    rl, rnd = by["procedures"]["RL"], by["procedures"]["random"]
    assert rl["up"] == 3 and rl["sign_p"] == pytest.approx(1 / 8) and rl["mean"] == pytest.approx(0.05)
    assert rnd["up"] == 1 and rnd["sign_p"] == pytest.approx(3 / 4)
    # RL's three parts are the 2nd-largest sum of the C(5, 3) = 10 ways to pick three (0.07+0.05+0.04 is larger)
    assert by["relabellings"] == 10 and by["permutation_p"] == pytest.approx(2 / 10)
    assert by["difference"] == pytest.approx(0.05 - 0.005)
    assert "permutation_p" not in compare_directions(result, {"RL": [1, 2, 3]})
    with pytest.raises(ConfigError, match="does not exist"):
        compare_directions(result, {"RL": [6]})
    with pytest.raises(ConfigError, match="in two procedures"):
        compare_directions(result, {"RL": [1, 2], "random": [2]})
