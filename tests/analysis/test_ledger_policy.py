import pytest
import torch
from omegaconf import OmegaConf

from analysis.ledger_policy import main
from worldenv_core.models.checkpoint import load_model, save_model
from worldenv_core.rl import es

LINEAR = {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}


def kept_run(tmp_path):
    """A starting policy, and a 2-iteration ledger written as a run writes it, with the run's weights."""
    torch.manual_seed(0)
    start = torch.nn.Linear(3, 2)
    save_model(tmp_path / "start", start, LINEAR, {"kind": "policy"})
    run, _ = load_model(tmp_path / "start")
    rl = OmegaConf.create({"es_sigma": 0.1, "es_step": 0.2, "es_top": None, "es_discount": 1.0, "es_parameters": "mean"})
    g, weights = torch.Generator().manual_seed(3), []
    for it in (1, 2):
        seeds = torch.randint(2**62, (2,), generator=g).tolist()
        success, steps = torch.rand(5, 4, generator=g) < 0.5, torch.randint(1, 40, (5, 4), generator=g)
        returns = es.member_returns(success, steps)
        es.ars_update(run, seeds, returns, rl.es_step, rl.es_top, rl.es_parameters)
        es.write_ledger_entry(tmp_path / "ledger", it, [it], seeds, success, steps, returns, rl)
        weights.append(run.weight.detach().clone())
    return weights


def test_the_written_policy_is_the_runs_at_the_chosen_iteration(tmp_path, capsys):
    weights = kept_run(tmp_path)
    for upto in (1, 2):
        main(["--policy", str(tmp_path / "start"), "--ledger", str(tmp_path / "ledger"), "--upto", str(upto),
              "--out", str(tmp_path / f"iter{upto}")])
        model, cfg = load_model(tmp_path / f"iter{upto}")
        assert torch.equal(model.weight, weights[upto - 1])
        assert cfg["meta"] == {"kind": "policy", "es_ledger": "ledger", "es_iterations": upto}
    assert str(tmp_path / "iter2") in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [(["--upto", "3"], "holds iterations 1..2"),
                                           (["--ledger", "nowhere"], "holds no iter_NNNN.json")])
def test_a_bad_request_is_one_line_before_any_work(tmp_path, capsys, args, message):
    kept_run(tmp_path)
    base = {"--policy": str(tmp_path / "start"), "--ledger": str(tmp_path / "ledger"), "--out": str(tmp_path / "o")}
    for flag, value in zip(args[::2], args[1::2]):
        base[flag] = value if flag != "--ledger" else str(tmp_path / value)
    with pytest.raises(SystemExit):
        main([x for kv in base.items() for x in kv])
    assert message in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_a_ledger_made_on_other_starting_weights_is_refused(tmp_path, capsys):
    """The folder names the weights its steps were made on (as a campaign's export writes it): another starting
    policy (a retrained SFT on a fresh machine) would silently become another policy, so it is one line instead."""
    kept_run(tmp_path)
    es.record_start(tmp_path / "ledger", "0123456789abcdef")
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path / "start"), "--ledger", str(tmp_path / "ledger"), "--out", str(tmp_path / "o")])
    assert "made on starting weights 0123456789abcdef" in capsys.readouterr().err and not (tmp_path / "o").exists()
