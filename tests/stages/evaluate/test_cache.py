"""Finished evaluation jobs are kept by what decides them: a killed evaluation resumes, and the same
weights evaluated the same way again (a LOOP that changed nothing) cost no real episode."""
import json
import shutil

import pytest

from stages.evaluate.cache import checkpoint_digest
from tests.stages.conftest import stage_cfg
from worldenv_core.manifest import Manifest


def test_a_checkpoint_is_named_by_its_weights_and_model_not_by_where_it_came_from(tmp_path, tiny_models):
    sft = next(p.parent for p in Manifest(tiny_models).resolve(Manifest(tiny_models).latest("train_policy"))
               if p.name == "model.safetensors")
    copy = shutil.copytree(sft, tmp_path / "post_trained")
    config = json.loads((copy / "config.json").read_text())
    config["meta"].update(step=40, iteration=40, post_trained_from=str(sft))  # what a LOOP with no update writes
    (copy / "config.json").write_text(json.dumps(config))
    assert checkpoint_digest(copy) == checkpoint_digest(sft)
    config["model"]["chunk"] = 4  # how it acts
    (copy / "config.json").write_text(json.dumps(config))
    assert checkpoint_digest(copy) != checkpoint_digest(sft)
    config["model"]["chunk"] = json.loads((sft / "config.json").read_text())["model"]["chunk"]
    (copy / "config.json").write_text(json.dumps(config))
    weights = bytearray((copy / "model.safetensors").read_bytes())
    weights[-1] ^= 1
    (copy / "model.safetensors").write_bytes(bytes(weights))
    assert checkpoint_digest(copy) != checkpoint_digest(sft)


@pytest.mark.sim
@pytest.mark.slow
def test_a_killed_evaluation_resumes_and_the_same_weights_are_not_run_again(tiny_models, monkeypatch):
    import stages.evaluate.run as evaluate_stage

    monkeypatch.setattr(evaluate_stage, "JOB_SIZE", 1)  # one job per init state
    exp = tiny_models
    common = ["policy_from=sft", "termination=oracle", "init_states=2", "workers=1", "progress=false",
              "videos_per_task=0", "task.max_steps=24"]  # short episodes: what is kept matters here, not success
    first = evaluate_stage.run(stage_cfg("evaluate", exp, *common))
    m = Manifest(exp)
    assert m.latest("evaluate", task="tiny").metrics["real_episodes"] == 2
    jobs = sorted((exp / "evaluate" / "jobs").glob("*.pkl.z"))
    assert len(jobs) == 2
    jobs[1].unlink()  # as if killed after its first job
    again = evaluate_stage.run(stage_cfg("evaluate", exp, *common))
    rec = Manifest(exp).latest("evaluate", task="tiny")
    assert rec.metrics["real_episodes"] == 1 and rec.metrics["reused_episodes"] == 1
    assert again["per_task"] == first["per_task"] and again["success_rate"] == first["success_rate"]
    evaluate_stage.run(stage_cfg("evaluate", exp, *common))  # all finished: no real episode
    assert Manifest(exp).latest("evaluate", task="tiny").metrics["real_episodes"] == 0
    evaluate_stage.run(stage_cfg("evaluate", exp, *common, "init_states=1", "reuse_jobs=false"))
    assert Manifest(exp).latest("evaluate", task="tiny").metrics["real_episodes"] == 1
