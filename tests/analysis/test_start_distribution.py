"""The start-distribution comparison: object ranges and the arm's mean gap in standard errors."""
import numpy as np
import pytest

from analysis.start_distribution import compare, main, mean_gap, yaw


def test_a_shifted_arm_joint_shows_as_a_gap_in_standard_errors_and_equal_objects_do_not():
    rng = np.random.default_rng(0)
    n_q = 1 + 9 + 7  # time, an arm of 2 joints here, one free object (7), then qvel ignored
    bench, fresh = rng.normal(0, 0.02, (50, n_q)), rng.normal(0, 0.02, (400, n_q))
    fresh[:, 1 + 1] += 0.05  # the second arm joint starts 0.05 rad off
    for states, turn in ((bench, 0.0), (fresh, 0.3)):  # the bowl turned about the vertical: 0 / 0.3 rad, near +-180 deg
        half = (np.pi + turn + rng.normal(0, 0.02, len(states))) / 2
        states[:, 1 + 2 + 3:1 + 2 + 7] = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], 1)
    rows = compare(bench, fresh, {"bowl": 2}, arm=[0, 1])
    assert [r[0] for r in rows] == ["bowl x", "bowl y", "bowl z", "bowl yaw (deg)", "arm joint 1", "arm joint 2"]
    assert abs(float(rows[4][4])) < 3 < float(rows[5][4])
    assert float(rows[3][3]) == pytest.approx(np.degrees(0.3), abs=1.0)  # not 360 - 17 degrees: wrapped around
    assert yaw(np.array([np.cos(0.25), 0, 0, np.sin(0.25)])) == pytest.approx(0.5)
    gap, z = mean_gap(bench[:, :3], bench[:, :3])
    assert np.allclose(gap, 0) and np.allclose(z, 0)


def test_too_few_fresh_placements_are_refused_before_any_reset(capsys):
    with pytest.raises(SystemExit):
        main(["--task", "5", "--fresh", "1"])
    assert "--fresh must be at least 2" in capsys.readouterr().err
