import numpy as np
import pytest
import torch

from analysis.update_similarity import cosines, main, weight_update
from worldenv_core.models.checkpoint import save_state

LINEAR = {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}


def test_weight_update_skips_integer_tensors_and_cosines_are_those_of_the_updates():
    base = {"w": torch.zeros(2, 2), "n": torch.tensor([3])}
    a = {"w": torch.tensor([[1.0, 0.0], [0.0, 0.0]]), "n": torch.tensor([5])}
    b = {"w": torch.tensor([[1.0, 1.0], [0.0, 0.0]]), "n": torch.tensor([3])}
    ua, ub = weight_update(base, a), weight_update(base, b)
    assert ua.tolist() == [1.0, 0.0, 0.0, 0.0]
    m = cosines([ua, ub, -ua, torch.zeros(4)])
    assert np.allclose(np.diag(m)[:3], 1.0) and m[0, 1] == pytest.approx(2 ** -0.5) and m[0, 2] == pytest.approx(-1.0)
    assert np.all(m[3] == 0.0) and np.all(m[:, 3] == 0.0)  # a run that moved nothing agrees with none


def test_cli_prints_the_cosine_table_and_needs_two_runs(tmp_path, capsys):
    torch.manual_seed(0)
    sft = torch.nn.Linear(3, 2)
    save_state(tmp_path / "sft", sft.state_dict(), LINEAR, {"kind": "policy"})
    for name, shift in (("a", 0.01), ("b", 0.02), ("c", -0.01)):
        save_state(tmp_path / name, {k: v + shift for k, v in sft.state_dict().items()}, LINEAR, {"kind": "policy"})
    main(["--policy", str(tmp_path / "sft"), "--like", *(str(tmp_path / n) for n in "abc")])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| (")]
    assert len(rows) == 3 and rows[0].endswith("| +1.000 | +1.000 | -1.000 |")
    with pytest.raises(SystemExit) as e:
        main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "a")])
    assert e.value.code == 2 and "two or more" in capsys.readouterr().err
