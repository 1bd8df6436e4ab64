"""Ledgers read within tasks, across tasks and under discounts: the rows, the files, and bad input named."""
import json

import pytest
import torch
from omegaconf import OmegaConf

from analysis.ledger_agreement import main
from worldenv_core.rl import es

RL = OmegaConf.create({"es_sigma": 0.05, "es_step": 0.05, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})


def write(folder, seed: int, opposed: bool) -> None:
    """Six iterations of 4 pairs on 32 consecutive placements of a 2-task suite (tasks alternate). A direction
    helps task 0 by `effect` and task 1 by `-effect` (opposed) or `+effect`; the member that helps is faster."""
    g = torch.Generator().manual_seed(seed)
    task = torch.arange(32) % 2
    for it in range(1, 7):
        effect = 0.3 * torch.randn(4, generator=g).clamp(-1.5, 1.5)
        per_task = torch.stack([effect, -effect if opposed else effect])  # (task, pair)
        gain = torch.stack([per_task, -per_task], 2).flatten(1)[task]  # (contexts, members)
        success = torch.rand(32, 8, generator=g) < 0.5 + gain
        steps = (120 - 60 * gain + 5 * torch.randn(32, 8, generator=g)).round().int()
        es.write_ledger_entry(folder, it, list(range(1000, 1032)), [it, it + 10, it + 20, it + 30], success, steps,
                              es.member_returns(success, steps), RL)


def test_directions_read_within_tasks_and_across_them(tmp_path, capsys):
    write(tmp_path / "opposed_ledger", 0, opposed=True)
    write(tmp_path / "shared_ledger", 1, opposed=False)
    rows = main([str(tmp_path / "opposed_ledger"), str(tmp_path / "shared_ledger"), "--tasks", "2",
                 "--discounts", "1", "0.97", "--json", str(tmp_path / "a.json"), "--markdown", str(tmp_path / "a.md")])
    by = {(r["ledger"], r["discount"]): r for r in rows}
    assert set(by) == {("opposed", 1.0), ("opposed", 0.97), ("shared", 1.0), ("shared", 0.97)}
    # a direction's effects on the two tasks cancel in a member's return over both; across the tasks they are opposed
    assert by["opposed", 1.0]["across_tasks"] < -0.5 and by["shared", 1.0]["across_tasks"] > 0.5
    assert by["shared", 1.0]["within_tasks"] > 0.5 > by["shared", 1.0]["within_tasks"] - 0.5 > by["opposed", 1.0]["within_tasks"]
    # the helping member is also the faster: a discounted return points where success does, on the other half
    assert by["shared", 0.97]["judged_by_success"] > 0.3
    # read as even against odd positions, the shared ledger's halves are its two tasks: the across-task figure
    shared = es.read_ledger(tmp_path / "shared_ledger")
    assert es.half_agreement(shared)["pooled"] == pytest.approx(es.half_agreement(shared, n_tasks=2, across_tasks=True)["pooled"])
    assert json.loads((tmp_path / "a.json").read_text()) == rows
    assert "| opposed | 6 | 1 |" in (tmp_path / "a.md").read_text()
    one_task = main([f"{tmp_path / 'shared_ledger'}:1", "--discounts", "1"])  # named as one task's run
    assert one_task[0]["tasks"] == 1 and one_task[0]["across_tasks"] is None
    for argv, msg in (([str(tmp_path / "shared_ledger"), "--discounts", "1.5"], "--discounts must lie in"),
                      ([str(tmp_path)], "no iter_NNNN.json"), ([f"{tmp_path / 'shared_ledger'}:0"], "at least one task")):
        with pytest.raises(SystemExit):
            main(argv)
        assert msg in capsys.readouterr().err

