"""Ledgers re-read under discounts: the rows, the files, and the bad input named."""
import json

import pytest
import torch
from omegaconf import OmegaConf

from analysis.discount_agreement import main
from worldenv_core.rl import es


def test_a_ledger_read_under_discounts(tmp_path, capsys):
    rl = OmegaConf.create({"es_sigma": 0.05, "es_step": 0.05, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})
    g = torch.Generator().manual_seed(0)
    folder = tmp_path / "toy_seed0_ledger"
    for it in range(1, 7):
        effect = torch.randn(4, generator=g)
        faster = torch.stack([effect, -effect], 1).flatten()  # the + member of a helpful direction is faster
        success = torch.rand(16, 8, generator=g) < 0.5
        steps = (120 - 30 * faster[None] + 5 * torch.randn(16, 8, generator=g)).round().int()
        es.write_ledger_entry(folder, it, list(range(16)), [it, it + 10, it + 20, it + 30], success, steps,
                              es.member_returns(success, steps), rl)
    rows = main([str(folder), "--discounts", "1", "0.95", "--json", str(tmp_path / "a.json"),
                 "--markdown", str(tmp_path / "a.md")])
    assert [(r["ledger"], r["discount"], r["iterations"]) for r in rows] == [("toy_seed0", 1.0, 6), ("toy_seed0", 0.95, 6)]
    assert rows[1]["agreement"] > rows[0]["agreement"] + 0.3  # the pace repeats on other starts; coin flips do not
    assert json.loads((tmp_path / "a.json").read_text()) == rows
    assert "| toy_seed0 | 6 | 0.95 |" in (tmp_path / "a.md").read_text()
    for argv, msg in (([str(folder), "--discounts", "1.5"], "--discounts must lie in"),
                      ([str(tmp_path)], "no iter_NNNN.json")):
        with pytest.raises(SystemExit):
            main(argv)
        assert msg in capsys.readouterr().err
