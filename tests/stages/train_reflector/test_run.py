"""train_reflector on the tiny task, then evaluate with termination=reflector, through the manifest."""
import json
from pathlib import Path

import pytest

from stages.evaluate.run import run as evaluate
from stages.train_reflector.run import run as train_reflector
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.data.selection import MissingEpisodesError
from worldenv_core.manifest import ArtefactError, Manifest
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.rl.termination import first_success
from worldenv_core.stage import ConfigError, compose_config

pytestmark = [pytest.mark.sim, pytest.mark.slow]
SMALL = ["train.steps=6", "train.batch_size=4", "train.log_every=2", "train.checkpoint_every=3", "holdout_every=2",
         "reflector.d_model=16", "reflector.layers=1", "reflector.heads=2", "reflector.frame_encoder.widths=[8,16]",
         "reflector.frame_encoder.keypoints=4", "plots=1", "train.mine.every=3", "eta_folds=0"]


def cfg(stage, exp, *overrides):
    return compose_config(stage, ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", *overrides])


@pytest.fixture(scope="module")
def trained(demo_experiment):
    metrics = train_reflector(cfg("train_reflector", demo_experiment, *SMALL, "expert_only=true"))
    return demo_experiment, metrics


def test_demos_go_on_after_success_for_the_reflector(demo_experiment):
    m = Manifest(demo_experiment)
    for path in m.resolve(m.latest("collect", task="tiny", source="expert"), kind="episodes"):
        ep = read_episode(path)
        assert first_success(ep.success) == ep.length - 8 and ep.success[-9:].all()


def test_train_reflector_records_checkpoint_and_report(trained, contract):
    exp, metrics = trained
    m = Manifest(exp)
    rec = m.latest("train_reflector", task="tiny", data="expert")
    assert rec.inputs == [m.latest("collect", task="tiny", source="expert").id]
    files = {p.name: p for p in m.resolve(rec)}
    assert {"model.safetensors", "config.json", "reflector_eval.json", "reflector_eval.md", "reflector_curves.png",
            "losses.png"} <= set(files)
    report = json.loads(files["reflector_eval.json"].read_text())
    real = report["real"]
    assert real["per_step"]["n"] > 0 and 0 <= real["per_step"]["accuracy"] <= 1
    assert real["termination"]["all"]["episodes"] == 1 == metrics["held_out"]
    assert "imagined" not in report  # this experiment has no world simulator
    model, meta = load_checkpoint(files["model.safetensors"].parent, "reflector", contract())
    # the training demo's 9 frames from success on, less the first 8: settled labels (train.label_delay=8)
    assert meta["held_out"] and meta["label_delay"] == 8 and meta["positive_frames"] == 9 - 8


def test_train_reflector_resumes_and_rejects_bad_settings(trained):
    exp, _ = trained
    train_reflector(cfg("train_reflector", exp, *SMALL, "expert_only=true"))  # finished, outputs intact: not run again
    assert Manifest(exp).latest("train_reflector").repeats
    # evaluation-only settings do not name the run: it is re-evaluated, not trained again
    assert train_reflector(cfg("train_reflector", exp, *SMALL, "expert_only=true", "plots=0"))["train_wall_s"] < 5
    with pytest.raises(ArtefactError, match="train_worldsim-000000000000"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "expert_only=true",
                            "imagined.worldsim_from=train_worldsim-000000000000"))
    with pytest.raises(ConfigError, match=r"eta .* must be in \[0, 1\], got 1.5"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "eta=1.5"))
    with pytest.raises(ConfigError, match="train.mine.every must .* divide train.checkpoint_every"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "train.mine.every=2"))
    with pytest.raises(ConfigError, match=r"eta_folds must be an integer >= 0, got -2"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "eta_folds=-2"))
    with pytest.raises(ConfigError, match=r"eta_folds must be 0 .* or at least 2"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "eta_folds=1"))
    with pytest.raises(ConfigError, match=r"eta_folds=2 needs 2 <= folds <= the 1 training episodes"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "expert_only=true", "eta_folds=2"))
    with pytest.raises(ConfigError, match=r"train.label_delay must be an integer >= 0, got -1"):
        train_reflector(cfg("train_reflector", exp, *SMALL, "train.label_delay=-1"))
    with pytest.raises(MissingEpisodesError, match="source=policy.*expert_only=true"):
        train_reflector(cfg("train_reflector", exp, *SMALL))


@pytest.fixture(scope="module")
def with_policy(trained):
    from stages.train_policy.run import run as train_policy

    exp, _ = trained
    train_policy(cfg("train_policy", exp, "train.steps=4", "scale_head.steps=2", "demos_per_task=1", "policy.hidden=32",
                     "policy.backbone.widths=[8,8,8,8]", "policy.backbone.keypoints=4"))
    return exp


def test_evaluate_with_reflector_termination(with_policy):
    exp = with_policy
    out = evaluate(cfg("evaluate", exp, "termination=reflector", "eta=0.0", "init_states=1", "workers=1",
                       "progress=false"))
    (ep,) = json.loads((Path(out["report_dir"]) / "episodes.json").read_text())
    assert ep["stop_step"] == ep["steps"] == 0  # eta = 0: R > 0 at the very first check stops the episode
    assert out["reflector_termination"]["episodes"] == 1
    report = (Path(exp) / "report" / "report.md").read_text()  # the experiment report includes this evaluation
    assert "sft / reflector" in report and "## Reflector" in report and (Path(exp) / "report" / "success.png").exists()
    used = Path(out["reflector"]).parts[-3:-1]  # the evaluation names its reflector's run; the reflector table lists it too
    assert report.count("/".join(used)) >= 2
    with pytest.raises(ConfigError, match=r"eta .* must be in \[0, 1\]"):
        evaluate(cfg("evaluate", exp, "termination=reflector", "eta=-1", "init_states=1"))


def test_evaluate_all_equals_three_separate_runs(with_policy):
    """termination=all reads oracle, fixed and reflector results off one rollout to the horizon;
    policy and simulator are deterministic, so they must equal three separate evaluations."""
    exp = with_policy
    reflector = Manifest(exp).latest("train_reflector", task="tiny").id  # by record id, as on the command line
    common = ["init_states=1", "workers=1", "progress=false", "videos_per_task=0", f"reflector_from={reflector}",
              "task.max_steps=64"]  # five evaluations: the same reading off a shorter horizon
    probe = evaluate(cfg("evaluate", exp, "termination=all", "eta=0.5", *common))
    (probe_ep,) = json.loads((Path(probe["reflector"]["report_dir"]) / "episodes.json").read_text())
    scores = sorted(probe_ep["reflector_scores"])
    eta = round(scores[len(scores) // 2], 4)  # a threshold some checks pass and some do not
    together = evaluate(cfg("evaluate", exp, "termination=all", f"eta={eta}", *common))
    keys = ("success", "steps", "stop_step", "first_success_step", "ever_succeeded")
    for mode in ("oracle", "fixed", "reflector"):  # one manifest record per mode, so the report finds each
        assert Manifest(exp).latest("evaluate", task="tiny", termination=mode).config["termination"] == "all"
    for mode in ("oracle", "fixed", "reflector"):
        alone = evaluate(cfg("evaluate", exp, f"termination={mode}", f"eta={eta}", *common))
        (a,) = json.loads((Path(alone["report_dir"]) / "episodes.json").read_text())
        (b,) = json.loads((Path(together[mode]["report_dir"]) / "episodes.json").read_text())
        assert {k: a[k] for k in keys} == {k: b[k] for k in keys}, mode
    assert together["fixed"]["per_task"][0]["mean_steps"] == 64


def test_lerobots_reward_classifier_trains_as_the_reflector_and_stops_an_evaluation(with_policy, contract):
    """`reflector=lerobot_classifier`: LeRobot's classifier trained by the same stage on the same labels,
    evaluated by the same report, and judging an evaluation's episodes through the same interface."""
    exp = with_policy
    tiny = ["reflector=lerobot_classifier", "reflector.encoder.embedding_size=8",
            "reflector.encoder.hidden_sizes=[8,16,16,16]", "reflector.hidden_dim=16", "reflector.latent_dim=16",
            "reflector.pooling_dim=2"]
    metrics = train_reflector(cfg("train_reflector", exp, *[s for s in SMALL if not s.startswith("reflector.")], *tiny,
                                  "expert_only=true"))
    rec = Manifest(exp).latest("train_reflector", task="tiny")
    assert rec.tags["reward"] == "LeRobot reward classifier" and metrics["steps"] == 6
    folder = next(p for p in Manifest(exp).resolve(rec) if p.name == "model.safetensors").parent
    model, _ = load_checkpoint(folder, "reflector", contract())
    assert type(model).__name__ == "LeRobotRewardClassifier"
    assert (folder.parent / "reflector_eval.json").exists() and metrics["held_out"] == 1
    out = evaluate(cfg("evaluate", exp, "termination=reflector", "eta=0.0", "init_states=1", "workers=1",
                       "progress=false", f"reflector_from={folder}", "videos_per_task=0"))
    (ep,) = json.loads((Path(out["report_dir"]) / "episodes.json").read_text())
    assert ep["stop_step"] == ep["steps"] == 0  # eta = 0: its first verdict (> 0) stops the episode


def test_a_refit_round_trains_on_every_policy_collection_each_counted(with_policy):
    """A refit round of the imagined route: an improved policy's rollouts (here a second noise scale) collect into
    a folder of their own; `policy_collections=all` trains on the newest of every folder, each an input whose real
    episodes count, where the default reads only the newest collection."""
    from stages.collect.run import run as collect

    exp = with_policy
    rollouts = ["source=policy", "episodes_per_task=1", "workers=1", "progress=false", "lerobot_export=false",
                "task.max_steps=16"]
    for noise in ("1.0", "3.0"):
        collect(cfg("collect", exp, *rollouts, f"noise_scale={noise}"))
    m = Manifest(exp)
    policy = {r.id for r in m.find("collect", task="tiny", source="policy")}
    assert len(policy) == 2
    both = train_reflector(cfg("train_reflector", exp, *SMALL, "policy_collections=all"))
    rec = m.latest("train_reflector", task="tiny")
    assert policy <= set(rec.inputs) and both["episodes"] + both["held_out"] == 2 + 2  # 2 demos, 1 rollout each
    assert sum(m.get(i).metrics["real_episodes"] for i in rec.inputs if i in policy) == 2
    newest = train_reflector(cfg("train_reflector", exp, *SMALL))
    assert len(policy & set(m.latest("train_reflector", task="tiny").inputs)) == 1
    assert newest["episodes"] + newest["held_out"] == 2 + 1
