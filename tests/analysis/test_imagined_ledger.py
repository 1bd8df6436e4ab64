"""A real ES ledger against its imagined replay: episode agreement and the step's cosine."""
import math

import pytest
import torch

from analysis.imagined_ledger import main, pair_differences, pooled, verdict_agreement


def test_an_imagined_verdict_equal_to_the_real_one_steps_the_same_way():
    real = torch.tensor([[1, 0, 1, 1], [0, 0, 1, 0]])  # 2 contexts x 2 pairs
    assert pair_differences(real).tolist() == [0.5, 0.5]
    r = verdict_agreement(real, real.clone())
    assert r["agreement"] == 1 and r["hack_rate"] == 0 and r["recall"] == 1 and r["step_cosine"] == pytest.approx(1)
    assert r["real_by_context"] == r["imagined_by_context"] == [0.75, 0.25]  # how far the start decides it


def test_the_step_cosine_reads_the_pairs_differences_not_the_success_rate():
    real = torch.tensor([[1, 0, 0, 1], [1, 0, 0, 1]])  # pair 0 +, pair 1 -
    flipped = torch.tensor([[0, 1, 1, 0], [0, 1, 1, 0]])  # the same success rate, every pair reversed
    r = verdict_agreement(real, flipped)
    assert r["imagined_success"] == r["real_success"] == 0.5
    assert r["step_cosine"] == pytest.approx(-1) and r["agreement"] == 0 and r["hack_rate"] == 1
    level = verdict_agreement(real, torch.ones_like(real))  # imagination calls everything a success: no step
    assert math.isnan(level["step_cosine"]) and level["recall"] == 1 and level["hack_rate"] == 0.5


def test_iterations_pool_their_episodes_and_their_steps():
    a = verdict_agreement(torch.tensor([[1, 0]]), torch.tensor([[1, 0]]))
    b = verdict_agreement(torch.tensor([[0, 1, 1, 0]]), torch.tensor([[1, 1, 1, 1]]))
    p = pooled([a, b])
    assert p["episodes"] == 6 and p["imagined_success"] == pytest.approx(5 / 6)
    assert p["hack_rate"] == pytest.approx(1 - 3 / 5) and p["recall"] == 1
    assert p["step_cosine"] == pytest.approx(1 / math.sqrt(3 * 1))  # dots 1 + 0; |real|^2 1 + 2, |imagined|^2 1 + 0
    assert "reward_step_cosine" not in p  # only where every iteration has the graded verdict
    a.update(reward_dot=0.5, reward_sq=0.25, imagined_reward=0.2)
    b.update(reward_dot=-1.0, reward_sq=1.0, imagined_reward=0.4)
    g = pooled([a, b])
    assert g["reward_step_cosine"] == pytest.approx(-0.5 / math.sqrt(3 * 1.25))
    assert g["imagined_reward"] == pytest.approx((0.2 * 2 + 0.4 * 4) / 6)


def test_outcomes_not_in_pairs_are_refused():
    with pytest.raises(ValueError, match="antithetic pairs"):
        verdict_agreement(torch.ones(2, 3), torch.ones(2, 3))


def test_the_cli_names_an_iteration_the_ledger_does_not_hold(tmp_path, capsys):
    ledger = tmp_path / "ledger"
    ledger.mkdir()
    (ledger / "iter_0001.json").write_text('{"iteration": 1, "seeds": [1], "success": [[1, 0]]}')
    with pytest.raises(SystemExit):
        main(["+task=tiny", "--ledger", str(ledger), "--policy", str(tmp_path), "--iterations", "2"])
    assert "the ledger holds iterations 1-1" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # keyframes: where they lie is checked before any model is loaded
        main(["+task=tiny", "--episodes", "x.mcap", "--policy", str(tmp_path), "--depth", "0.6", "0.2"])
    assert "--depth: a context depth [lo, hi] needs 0 <= lo < hi <= 1" in capsys.readouterr().err


def _result(rows: dict, worldsim: str = "w") -> dict:
    return {"ledger": "l", "episodes": None, "policy": "p", "worldsim": worldsim, "robot_layer": False, "reflector": "r",
            "eta": 0.5, "horizon": 8, "iterations": rows, "pooled": pooled(list(rows.values()))}


def test_results_of_disjoint_iterations_merge_into_the_one_run_over_all(tmp_path):
    import json

    a = verdict_agreement(torch.tensor([[1, 0]]), torch.tensor([[1, 0]]))
    b = verdict_agreement(torch.tensor([[0, 1, 1, 0]]), torch.tensor([[1, 1, 1, 1]]))
    c = verdict_agreement(torch.tensor([[1, 1]]), torch.tensor([[0, 1]]))
    parts = []
    for k, rows in enumerate([{"20": b}, {"1": a, "5": c}]):  # written as the CLI writes them, keys as strings
        parts.append(tmp_path / f"part{k}.json")
        parts[-1].write_text(json.dumps(_result(rows)))
    merged = main(["--merge", *map(str, parts), "--json", str(tmp_path / "all.json")])
    assert list(merged["iterations"]) == ["1", "5", "20"]  # in iteration order
    assert merged["pooled"] == pytest.approx(pooled([a, c, b]), nan_ok=True)
    assert json.loads((tmp_path / "all.json").read_text())["pooled"] == pytest.approx(merged["pooled"], nan_ok=True)


def test_results_of_other_replays_or_the_same_iteration_twice_are_refused(tmp_path, capsys):
    import json

    a = verdict_agreement(torch.tensor([[1, 0]]), torch.tensor([[1, 0]]))
    for name, result in [("x", _result({"1": a})), ("y", _result({"2": a}, worldsim="other")), ("z", _result({"1": a}))]:
        (tmp_path / f"{name}.json").write_text(json.dumps(result))
    (tmp_path / "bad.json").write_text("{}")
    out = str(tmp_path / "all.json")
    for parts, message in [(["x", "y"], "the results differ in worldsim"), (["x", "z"], "iteration(s) 1 appear in two"),
                           (["x", "bad"], "not an imagined_ledger --json result")]:
        with pytest.raises(SystemExit):
            main(["--merge", *(str(tmp_path / f"{p}.json") for p in parts), "--json", out])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the merged result must go somewhere
        main(["--merge", str(tmp_path / "x.json")])
    assert "--merge needs --json" in capsys.readouterr().err
