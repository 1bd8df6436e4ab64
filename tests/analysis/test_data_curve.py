"""The data curve: kept paired-replay runs read into one table and figure by exploration rollouts."""
import json

import pytest
import torch

from analysis.data_curve import data_curve, main, table
from analysis.imagined_ledger import pooled, verdict_agreement


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
    assert "| mean | 250 | 80 | 0.00 | 0.36 | 0.74 | 0.50 | 0.70 | - | - | evaluate_imagination-b |" in text  # nan: no hack
    out = main(["--point", "0", "mean", str(a), "--point", "250", "mean", str(b), "--json", str(tmp_path / "c.json"),
                "--plot", str(tmp_path / "c.png")])
    assert json.loads((tmp_path / "c.json").read_text())["mean"][0]["hack_rate"] == 0.30 == out["mean"][0]["hack_rate"]
    assert (tmp_path / "c.png").stat().st_size > 0


def test_a_folder_without_a_run_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no fidelity.json in .*empty"):
        data_curve([(0, "mean", tmp_path / "empty")])
    with pytest.raises(ValueError, match=">= 0"):
        data_curve([(-1, "mean", _run(tmp_path / "x", 0, 0, 0.5, 0, "r"))])


def test_an_es_ledger_replay_from_starts_is_a_point_with_its_step_cosine(tmp_path):
    """imagined_ledger's json (ES members from their placements' starts) reads as a point in the same terms: its hacks
    and precision from the episodes, the share of placements split in imagination, the step's cosine; no AUROC."""
    real = torch.tensor([[1, 0, 1, 0], [0, 0, 1, 1]])        # 2 placements x 2 antithetic pairs
    imagined = torch.tensor([[1, 1, 1, 1], [1, 0, 1, 0]])    # placement 1 all success, placement 2 split
    row = verdict_agreement(real, imagined)
    path = tmp_path / "imagined_ledger_x.json"
    path.write_text(json.dumps({"iterations": {"1": row}, "pooled": pooled([row])}))
    curves = data_curve([(0, "from starts", path)])
    point = curves["from starts"][0]
    assert point["rollouts"] == 8 and point["imagined_success"] == 0.75 and point["real_success"] == 0.5
    assert point["hacks"] == 6 - 3 and point["precision"] == 0.5 and point["hack_rate"] == 0.5  # 3 of 6 hold
    assert point["imagined_mixed_groups"] == 0.5 and point["auroc"] is None and point["record"] == "imagined_ledger_x"
    assert point["step_cosine"] == row["step_cosine"]
    assert f"| 0.50 | {point['step_cosine']:.2f} / - | imagined_ledger_x |" in table(curves)
    main(["--point", "0", "from starts", str(path), "--plot", str(tmp_path / "p.png")])  # no AUROC line to draw
    assert (tmp_path / "p.png").stat().st_size > 0
    (tmp_path / "other.json").write_text("{}")
    with pytest.raises(ValueError, match="not an imagined_ledger"):
        data_curve([(0, "from starts", tmp_path / "other.json")])
