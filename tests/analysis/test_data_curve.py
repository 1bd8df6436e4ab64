"""The data curve: kept paired-replay runs read into one table and figure by exploration rollouts."""
import json

import pytest

from analysis.data_curve import data_curve, main, table


def _run(folder, imagined, real, auroc, hack, record):
    folder.mkdir(parents=True)
    headline = {"rollouts": 80, "imagined_success": imagined, "real_success": real, "auroc": auroc, "recall": 0.5,
                "precision": 0.7, "hack_rate": hack, "hacks": 3, "imagined_mixed_groups": 0.2}
    (folder / "fidelity.json").write_text(json.dumps({"headline": headline, "record": record}))
    return folder


def test_points_sort_by_rollouts_per_generator_and_render(tmp_path):
    a = _run(tmp_path / "a", 0.575, 0.463, 0.83, 0.30, "evaluate_imagination-a")
    b = _run(tmp_path / "b", 0.0, 0.363, 0.74, float("nan"), "evaluate_imagination-b")
    c = _run(tmp_path / "c", 0.163, 0.463, 0.82, 0.23, "evaluate_imagination-c")
    curves = data_curve([(250, "mean", b), (0, "mean", a), (250, "sampled", c)])
    assert [r["exploration_rollouts"] for r in curves["mean"]] == [0, 250]
    assert curves["mean"][1]["auroc"] == 0.74 and curves["sampled"][0]["record"] == "evaluate_imagination-c"
    text = table(curves)
    assert "| mean | 250 | 80 | 0.00 | 0.36 | 0.74 | 0.50 | 0.70 | - | evaluate_imagination-b |" in text  # nan: no hack
    out = main(["--point", "0", "mean", str(a), "--point", "250", "mean", str(b), "--json", str(tmp_path / "c.json"),
                "--plot", str(tmp_path / "c.png")])
    assert json.loads((tmp_path / "c.json").read_text())["mean"][0]["hack_rate"] == 0.30 == out["mean"][0]["hack_rate"]
    assert (tmp_path / "c.png").stat().st_size > 0


def test_a_folder_without_a_run_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no fidelity.json in .*empty"):
        data_curve([(0, "mean", tmp_path / "empty")])
    with pytest.raises(ValueError, match=">= 0"):
        data_curve([(-1, "mean", _run(tmp_path / "x", 0, 0, 0.5, 0, "r"))])
