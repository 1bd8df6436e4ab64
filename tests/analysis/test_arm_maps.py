"""The arm skeleton's figures of merit on recorded episodes: joints tracked from end-effector states, links
against the simulator's segmentation of the robot."""
import json

import pytest

from analysis.arm_maps import main


def test_a_folder_without_episodes_is_one_line_naming_it(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main([str(tmp_path)])
    assert f"no episodes under {tmp_path}" in capsys.readouterr().err


@pytest.mark.sim
@pytest.mark.slow
def test_tracking_and_coverage_on_a_recorded_demo(demo_experiment, tmp_path):
    out, figure = tmp_path / "arm.json", tmp_path / "arm.jpg"
    result = main([str(demo_experiment / "data"), "--episodes", "1", "--every", "40", "--out", str(out),
                   "--figure", str(figure)])
    assert json.loads(out.read_text()) == result and figure.stat().st_size > 0
    assert result["steps_tracked"] > 50 and result["tracking_mm"]["median"] < 2.0
    assert result["coverage"]["recall_mean"] > 0.6 and result["coverage"]["precision_mean"] > 0.6
