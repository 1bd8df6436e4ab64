import json

import pytest
import torch

from analysis.validation import main, summary_line
from stages.post_train_loop.evaluation import validation_key
from worldenv_core.models.checkpoint import save_model
from worldenv_core.stage import compose_config, task_contract

LINEAR = {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}


def test_a_policy_a_run_validated_is_read_back_from_the_runs_cache(tmp_path, capsys):
    """The cache is the one the runs write (<experiment>/post_train_loop/validation_cache, keyed by weights,
    contract and set size): a policy already validated costs no episode, and its figure is the run's."""
    torch.manual_seed(0)
    policy = save_model(tmp_path / "policy", torch.nn.Linear(3, 2), LINEAR, {"kind": "policy"})
    overrides = ["+task=tiny", f"experiment_dir={tmp_path / 'exp'}"]
    key = validation_key(str(policy), task_contract(compose_config("post_train_loop", ["scale=small", *overrides])), 4)
    cache = tmp_path / "exp" / "post_train_loop" / "validation_cache"
    cache.mkdir(parents=True)
    kept = {"validation_success": 0.75, "validation_task0": 0.75, "validation_episodes": 4}
    (cache / f"{key}.json").write_text(json.dumps(kept))
    out = main(["--policy", str(policy), "--episodes", "4", "--json", str(tmp_path / "v.json"), *overrides])
    result = out[str(policy)]
    assert result["validation_success"] == 0.75 and result["validation_cached"] == 1.0
    assert result["validation_episodes"] == 0 and result["validation_n"] == 4
    assert json.loads((tmp_path / "v.json").read_text())[str(policy)]["validation_success"] == 0.75
    assert "0.75 (95 % 0.30-0.95, 4 placements, cached); tasks 75 %" in capsys.readouterr().out


def test_summary_orders_tasks_by_number():
    line = summary_line("p", {"validation_success": 0.5, "validation_n": 20.0,
                              **{f"validation_task{t}": t / 10 for t in (10, 2, 1)}})
    assert line.endswith("tasks 10 / 20 / 100 %")


@pytest.mark.parametrize("args, message", [(["--policy", "nowhere"], "no model.safetensors there"),
                                           (["--episodes", "0"], "--episodes must be > 0")])
def test_a_bad_request_is_one_line_before_any_work(tmp_path, capsys, args, message):
    save_model(tmp_path / "policy", torch.nn.Linear(3, 2), LINEAR, {"kind": "policy"})
    base = {"--policy": str(tmp_path / "policy"), "--episodes": "4"}
    base.update(dict(zip(args[::2], [str(tmp_path / a) if a == "nowhere" else a for a in args[1::2]])))
    with pytest.raises(SystemExit):
        main([x for kv in base.items() for x in kv] + ["+task=tiny", f"experiment_dir={tmp_path / 'exp'}"])
    assert message in capsys.readouterr().err
