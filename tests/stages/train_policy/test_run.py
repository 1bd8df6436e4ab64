"""train_policy -> collect source=policy -> evaluate on the tiny task, through the manifest."""
import json
from pathlib import Path

import pytest
from stages.collect.run import run as collect
from analysis import keep, paired
from stages.evaluate.run import run as evaluate
from stages.train_policy.run import run as train_policy
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.manifest import ArtefactError, Manifest
from stages.evaluate.evaluation import success_table
from worldenv_core.report import ReportContext
from worldenv_core.stage import ConfigError, compose_config

pytestmark = [pytest.mark.sim, pytest.mark.slow]


HORIZON = 48  # evaluated and collected episodes: the plumbing, not 280 steps of a policy that fails


def cfg(stage, exp, *overrides):
    episodes = [f"task.max_steps={HORIZON}"] if stage in ("evaluate", "collect") else []
    return compose_config(stage, ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", *episodes, *overrides])


@pytest.fixture(scope="module")
def experiment(demo_experiment):
    exp = demo_experiment
    small = ["train.steps=20", "scale_head.steps=10", "train.log_every=5", "train.checkpoint_every=10",
             "demos_per_task=1", "policy.hidden=64", "policy.backbone.widths=[8,16,16,16]", "policy.backbone.keypoints=8"]
    metrics = train_policy(cfg("train_policy", exp, *small))
    return exp, metrics, small


def test_train_policy_records_a_loadable_checkpoint_and_a_loss_plot(experiment):
    exp, metrics, _ = experiment
    m = Manifest(exp)
    rec = m.latest("train_policy", task="tiny", scale="tiny")
    assert rec.inputs == [m.latest("collect", task="tiny", source="expert").id]
    files = {p.name for p in m.resolve(rec)}
    assert {"model.safetensors", "config.json", "losses.png"} <= files
    assert metrics["final_l1"] is not None and metrics["final_nll"] is not None


def test_train_policy_resumes_from_its_last_checkpoint(experiment):
    exp, _, small = experiment
    # Same settings and inputs, outputs intact: the finished run is not repeated; its record hands it on
    first = Manifest(exp).latest("train_policy")
    assert train_policy(cfg("train_policy", exp, *small)) == first.metrics
    assert Manifest(exp).latest("train_policy").repeats == (first.repeats or first.id)
    # shown otherwise (another logger): the same work dir, finished, so it resumes at the end and only re-saves
    metrics = train_policy(cfg("train_policy", exp, *small, "logger=none"))
    assert metrics["train_wall_s"] < 5 and not Manifest(exp).latest("train_policy").repeats


def test_too_few_demos_is_a_clear_error(experiment):
    exp, _, small = experiment
    with pytest.raises(ConfigError, match="demos_per_task=3.*only"):
        train_policy(cfg("train_policy", exp, *small[:-1], "demos_per_task=3"))


@pytest.mark.parametrize("termination", ["oracle", "fixed"])
def test_evaluate_in_both_termination_modes(experiment, termination):
    exp, _, _ = experiment
    out = evaluate(cfg("evaluate", exp, f"termination={termination}", "init_states=1", "workers=1", "progress=false"))
    (row,) = out["per_task"]
    assert row["n"] == 1 and 0.0 <= out["success_rate"] <= 1.0
    (ep,) = json.loads((Path(out["report_dir"]) / "episodes.json").read_text())
    assert ep["init_state"] == 0
    if termination == "fixed" or not ep["success"]:  # no stop signal: the episode runs to the horizon
        assert ep["steps"] == HORIZON
    assert Manifest(exp).latest("evaluate", task="tiny", termination=termination).files("video")


def test_policy_rollouts_keep_every_episode_with_mu_and_beta(experiment):
    exp, _, _ = experiment
    out = collect(cfg("collect", exp, f"data_dir={exp / 'data'}", "source=policy", "episodes_per_task=2",
                      "noise_scale=[1.0,3.0]", "workers=1", "progress=false", "lerobot_export=false"))
    assert out["collection"]["kept"] == 2
    rec = Manifest(exp).latest("collect", task="tiny", source="policy")
    eps = [read_episode(p) for p in sorted(Manifest(exp).resolve(rec, kind="episodes"))]
    for ep in eps:
        assert ep.meta.source == "policy" and set(ep.step_extras) == {"mu", "beta"}
        assert ep.step_extras["mu"].shape == (ep.length, 7)
    # several noise scales are cycled over the episodes (more varied on-policy data)
    assert [ep.meta.extra["noise_scale"] for ep in eps] == ["1.0", "3.0"]
    with pytest.raises(ConfigError, match="noise_scale must be a number > 0 or a list"):
        collect(cfg("collect", exp, "source=policy", "noise_scale=[1.0,0]"))


def test_evaluate_without_a_policy_names_the_missing_stage(tmp_path):
    with pytest.raises(ArtefactError, match="no 'train_policy' artefact"):
        evaluate(cfg("evaluate", tmp_path, "init_states=1", "progress=false"))
    with pytest.raises(ConfigError, match="termination must be one of oracle, fixed"):
        evaluate(cfg("evaluate", tmp_path, "termination=never"))
    with pytest.raises(ConfigError, match="policy_label must be one of"):
        evaluate(cfg("evaluate", tmp_path, "policy_label=best"))
    with pytest.raises(ConfigError, match="first_init_state \\+ init_states is at most 50"):
        evaluate(cfg("evaluate", tmp_path, "first_init_state=49", "init_states=2"))


def test_a_released_checkpoint_folder_fills_its_named_column(experiment):
    """make eval-release: a policy given as a folder is tabled as the policy it is labelled."""
    exp, _, _ = experiment
    folder = next(p.parent for p in Manifest(exp).resolve(Manifest(exp).latest("train_policy", task="tiny"))
                  if p.name == "model.safetensors")
    evaluate(cfg("evaluate", exp, f"policy_from={folder}", "policy_label=post_trained", "termination=fixed",
                 "init_states=1", "workers=1", "progress=false", "videos_per_task=0"))
    rec = Manifest(exp).latest("evaluate", task="tiny", policy="post_trained")
    _, cells = success_table(ReportContext(Manifest(exp), "tiny", exp / "report"))
    assert rec.tags["termination"] == "fixed" and ("post_trained", "fixed") in cells


def test_evaluate_on_another_registered_suite_with_the_same_tasks(experiment):
    exp, _, _ = experiment
    own = Manifest(exp).latest("evaluate", task="tiny", termination="fixed")
    out = evaluate(cfg("evaluate", exp, "eval_suite=libero_object_lan", "eval_max_steps=24", "termination=fixed",
                       "init_states=1", "workers=1", "progress=false", "videos_per_task=0"))
    assert out["suite"] == "libero_object_lan" and out["max_steps"] == 24 and out["episodes"] == 1
    (ep,) = json.loads((Path(out["report_dir"]) / "episodes.json").read_text())
    assert ep["steps"] == 24
    m = Manifest(exp)
    rec = m.latest("evaluate", task="tiny", eval_suite="libero_object_lan")
    assert rec.tags["termination"] == "fixed"
    report = (exp / "report" / "report.md").read_text()
    assert "## Evaluated on other suites" in report and "| sft | libero_object_lan | fixed | 24 |" in report
    # the task's own table still shows its own suite's evaluation
    _, cells = success_table(ReportContext(m, "tiny", exp / "report"))
    assert own.id != rec.id and cells[("sft", "fixed")]["suite"] == "libero_object"


def test_a_later_init_state_range_pools_with_the_first_into_one_paired_comparison(experiment):
    exp, _, _ = experiment
    run = ("termination=fixed", "init_states=1", "workers=1", "progress=false", "videos_per_task=0")
    first = evaluate(cfg("evaluate", exp, *run))
    later = evaluate(cfg("evaluate", exp, *run, "first_init_state=1"))
    (ep,) = json.loads((Path(later["report_dir"]) / "episodes.json").read_text())
    assert ep["init_state"] == 1 and later["first_init_state"] == 1
    m = Manifest(exp)
    later_id = m.latest("evaluate", task="tiny", first_init_state=1).id
    first_id = next(r.id for r in reversed(m.find("evaluate", task="tiny", termination="fixed"))
                    if r.metrics.get("report_dir") == first["report_dir"])
    # the report's tables stay those of the first N init states
    _, cells = success_table(ReportContext(m, "tiny", exp / "report"))
    assert cells[("sft", "fixed")]["report_dir"] == first["report_dir"]
    out = paired.main([str(exp), "--a", first_id, later_id, "--b", later_id, first_id, "--json", str(exp / "p.json")])
    assert out["episodes"] == 2 and out["only_a"] == out["only_b"] == 0 and out["p_value"] == 1.0
    assert json.loads((exp / "p.json").read_text())["a_records"] == [first_id, later_id]
    # output folders (as kept in the repository) name evaluations without their manifest
    folders = [first["report_dir"], later["report_dir"]]
    assert paired.main(["-", "--a", *folders, "--b", *folders[::-1]])["episodes"] == 2
    # kept in the repository: no machine path, and pooled as the experiment's own
    kept = keep.main([str(exp), first_id, later_id, "--into", str(exp / "kept")])
    text = (kept[0] / "results.json").read_text()
    assert str(exp) not in text and json.loads(text)["record"] == first_id
    assert paired.main(["-", "--a", *map(str, kept), "--b", *folders])["episodes"] == 2
    # a policy is its weights: the same weights under another name (released, copied) pool, other weights do not
    renamed = json.loads((kept[1] / "results.json").read_text())
    assert len(renamed["policy_digest"]) == 64
    renamed["policy"] = "checkpoints/tiny/released"
    (kept[1] / "results.json").write_text(json.dumps(renamed))
    assert paired.main(["-", "--a", *map(str, kept), "--b", *folders])["episodes"] == 2
    (kept[1] / "results.json").write_text(json.dumps({**renamed, "policy_digest": "0" * 64}))
    with pytest.raises(ConfigError, match="other weights"):
        paired.main(["-", "--a", *map(str, kept), "--b", *folders])
    with pytest.raises(ConfigError, match="no experiment directory"):
        paired.main(["-", "--a", first_id, "--b", *folders])
    with pytest.raises(ConfigError, match="init state 0 is in"):
        paired.main([str(exp), "--a", first_id, first_id, "--b", later_id])
    with pytest.raises(ConfigError, match="share no episode"):
        paired.main([str(exp), "--a", first_id, "--b", later_id])
    oracle = evaluate(cfg("evaluate", exp, *run[1:], "termination=oracle"))
    oracle_id = next(r.id for r in reversed(Manifest(exp).find("evaluate", task="tiny", termination="oracle"))
                     if r.metrics.get("report_dir") == oracle["report_dir"])
    with pytest.raises(ConfigError, match="not the same episodes"):
        paired.main([str(exp), "--a", oracle_id, "--b", first_id])


def test_a_lerobot_act_policy_trains_and_evaluates_through_the_same_stages(experiment):
    """`policy=lerobot_act`: LeRobot's ACT trained by train_policy's two phases from the same demos, its
    folder also in LeRobot's own layout (ACTPolicy.from_pretrained reads it), evaluated by `evaluate`,
    its perturbed rollouts collected, and post-trained by LOOP in the real simulator.
    (Last in this file: it becomes the experiment's latest train_policy.)"""
    import torch
    from lerobot.policies.act.modeling_act import ACTPolicy

    from worldenv_core.models.checkpoint import load_checkpoint

    exp, _, _ = experiment
    act = ["policy=lerobot_act", "policy.dim_model=16", "policy.n_heads=2", "policy.dim_feedforward=32",
           "policy.n_encoder_layers=1", "train.steps=4", "scale_head.steps=2", "train.log_every=2",
           "train.checkpoint_every=2", "demos_per_task=1"]
    metrics = train_policy(cfg("train_policy", exp, *act))
    m = Manifest(exp)
    rec = m.latest("train_policy", task="tiny", scale="tiny")
    folder = next(p for p in m.resolve(rec) if p.name == "model.safetensors").parent
    assert metrics["final_l1"] is not None and metrics["final_nll"] is not None
    assert (folder / "lerobot" / "config.json").exists() and len(rec.files("lerobot_checkpoint")) == 2  # recorded
    policy, meta = load_checkpoint(folder, "policy")
    assert type(policy).__name__ == "ACTLaplacePolicy" and meta["chunk"] == policy.chunk
    native = ACTPolicy.from_pretrained(folder / "lerobot").eval()
    images = {"agentview": torch.randint(0, 256, (1, 3, 64, 64), dtype=torch.uint8)}
    batch = policy.inputs(images, torch.zeros(1, 7), torch.zeros(1, 384))
    assert torch.allclose(native.model(batch)[0], policy(images, torch.zeros(1, 7), torch.zeros(1, 384))[0], atol=1e-5)
    out = evaluate(cfg("evaluate", exp, f"policy_from={folder}", "termination=oracle", "init_states=1", "workers=1",
                       "progress=false", "videos_per_task=0"))
    (row,) = out["per_task"]
    assert row["n"] == 1 and 0.0 <= out["success_rate"] <= 1.0
    # its Laplace-perturbed rollouts are collected as the project's policy's are (mu and beta per step)
    got = collect(cfg("collect", exp, f"data_dir={exp / 'data_act'}", "source=policy", f"policy_from={folder}",
                      "episodes_per_task=1", "workers=1", "progress=false", "lerobot_export=false"))
    (path,) = Manifest(exp).resolve(Manifest(exp).latest("collect", task="tiny", source="policy"), kind="episodes")
    ep = read_episode(path)
    assert got["collection"]["kept"] == 1 and ep.step_extras["mu"].shape == (ep.length, 7)
    # and post-trained by LOOP (the real route from fresh placements), PPO's first ratio exactly 1
    from stages.post_train_loop.run import run as post_train_loop

    loop = post_train_loop(cfg("post_train_loop", exp, "env=real", "rl.contexts=placements", f"policy_from={folder}",
                               "rl.iterations=1", "rl.contexts_per_iteration=1", "rl.n_rollouts=2", "rl.horizon=8",
                               "rl.minibatch=2", "rl.filter_groups=false", "eval.every=0", "eval.init_states=0",
                               "eval.workers=1", "progress=false"))
    assert loop["train_real_episodes"] == 2
    rec = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    trained = next(p for p in Manifest(exp).resolve(rec) if p.name == "model.safetensors").parent
    history = json.loads((trained.parent / "training.json").read_text())
    step = next(h for h in history if "mean_reward" in h)
    assert step["ratio_mean"] == pytest.approx(1.0, abs=0.05) and step["approx_kl"] >= 0
    after, _ = load_checkpoint(trained, "policy")
    assert type(after).__name__ == "ACTLaplacePolicy" and (trained / "lerobot" / "config.json").exists()
    assert ACTPolicy.from_pretrained(trained / "lerobot") is not None  # the post-trained policy, LeRobot's layout
    # and by the recipe that learns (ES in weight space): members of ACT's weights, the scale head untouched
    es_run = post_train_loop(cfg("post_train_loop", exp, "env=real", "rl=es", f"policy_from={folder}", "rl.iterations=1",
                                 "rl.contexts_per_iteration=1", "rl.es_pairs=1", "rl.horizon=8", "eval.every=0",
                                 "eval.init_states=0", "eval.workers=1", "progress=false"))
    assert es_run["train_real_episodes"] == 2
    rec = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    stepped = next(p for p in Manifest(exp).resolve(rec) if p.name == "model.safetensors").parent
    after, _ = load_checkpoint(stepped, "policy")
    moved = {n for (n, a), (_, b) in zip(policy.named_parameters(), after.named_parameters()) if not a.equal(b)}
    assert type(after).__name__ == "ACTLaplacePolicy" and not any(n.startswith("scale_head.") for n in moved)
    assert ACTPolicy.from_pretrained(stepped / "lerobot") is not None
