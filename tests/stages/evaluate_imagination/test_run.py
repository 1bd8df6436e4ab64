"""evaluate_imagination on the tiny task: the SFT policy at two noise scales in imagination, each
imagined rollout replayed in the real simulator, the verdict table, the accounting, resume and
bad settings."""
import json
from pathlib import Path

import numpy as np
import pytest

from stages.evaluate_imagination.run import run as evaluate_imagination
from tests.stages.conftest import stage_cfg
from worldenv_core.manifest import Manifest
from worldenv_core.stage import ConfigError

pytestmark = [pytest.mark.sim, pytest.mark.slow]
PAIRED = ["horizon=16", "contexts.init_states=1", "contexts.episodes_per_task=1", "contexts.episode_frames=1",
          "rollouts=2", "closed_loop_rollouts=1", "noise_scales=[1.0,3.0]", "horizons=[8,16]", "gifs=1", "workers=1",
          "progress=false"]


@pytest.fixture(scope="module")
def paired(tiny_models):
    return tiny_models, evaluate_imagination(stage_cfg("evaluate_imagination", tiny_models, *PAIRED))


def test_every_imagined_rollout_is_paired_with_its_real_replay(paired):
    exp, summary = paired
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    assert {Manifest(exp).get(i).stage for i in rec.inputs} >= {"train_policy", "train_worldsim", "train_reflector"}
    # 2 contexts (init state 0, a frame of the held-out demo) x 2 rollouts, for each of 2 noise scales; the
    # first (paired_policies=1) replayed in the real simulator, both run closed loop once per context
    assert list(summary["per_policy"]) == ["sft@1", "sft@3"] and summary["headline_policy"] == "sft@1"
    assert summary["headline"]["rollouts"] == 4 and summary["imagined_rollouts"] == 8
    # replays + closed loop + the mid-episode context's prefix checked once before any imagination
    assert summary["real_episodes"] == 4 + 2 * 2 + 1 == rec.metrics["real_episodes"] and summary["contexts_dropped"] == []
    assert summary["per_policy"]["sft@3"]["rollouts"] == 0 and 0 <= summary["per_policy"]["sft@3"]["imagined_success"] <= 1
    pairs = json.loads(next(Path(exp, a.path) for a in rec.files("report") if a.path.endswith("pairs.json")).read_text())
    rows = pairs["sft@1"]["rows"]
    assert pairs["sft@3"]["rows"] == [] and len(pairs["sft@3"]["closed_loop"]) == 2
    assert [r["context_kind"] for r in rows] == ["init", "init", "episode", "episode"]
    assert rows[0]["start"] == rows[1]["start"] == "task0/init0"  # an init state is one per task: its key names it
    for r in rows:  # watched to the horizon in imagination and replayed to it in reality
        assert r["real_error"] is None and r["steps"] == 16 and len(r["imagined_scores"]) == len(r["real_scores"]) == 3
        assert all(0.0 <= x <= 1.0 for x in r["imagined_scores"] + r["real_scores"])
        assert set(r["frames"]) <= {"8", "16"} and all(len(v) == 2 for v in r["frames"].values())
    assert summary["frames"][8]["n"] == 4 and np.isfinite(summary["frames"][8]["model_ssim"])
    assert 0.0 <= summary["headline"]["imagined_success"] <= 1.0 and summary["evaluator"]["policies"] == 2
    assert len(rec.files("video")) == 1 and len(rec.files("plot")) == 2  # per policy; verdict vs eta
    assert [c["eta"] for c in summary["eta_curve"]][:2] == [0.05, 0.1] and len(summary["eta_curve"]) == 19
    assert summary["replay_eta"]["folds"] == 2 and len(summary["replay_eta"]["etas"]) == 2


def test_a_reflector_named_later_judges_the_stored_pairs_without_a_rollout(paired):
    exp, summary = paired
    # the terminating reflector named again as a further judge: on the same stored frames, the same verdicts
    rid = Manifest(exp).latest("train_reflector", task="tiny").id
    judged_run = evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, f"more_reflectors=[{rid}]"))
    assert json.dumps(judged_run["headline"]) == json.dumps(summary["headline"])  # the pairs were reused
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    pairs = json.loads(next(Path(exp, a.path) for a in rec.files("report") if a.path.endswith("pairs.json")).read_text())
    for r in pairs["sft@1"]["rows"]:
        (more,) = r["more_reflectors"].values()
        assert more["imagined_scores"] == pytest.approx(r["imagined_scores"], abs=1e-4)
        assert more["real_scores"] == pytest.approx(r["real_scores"], abs=1e-4)
    (judged,) = judged_run["judges"].values()
    assert judged["eta"] == summary["eta"] and judged["rollouts"] == summary["headline"]["rollouts"]
    for key in ("imagined_success", "real_success", "real_frames_f1", "max_task_gap"):
        assert judged[key] == pytest.approx(summary["headline"][key], nan_ok=True)
    section = (Path(exp) / "report" / "report.md").read_text().split("## Verdict fidelity")[1].split("\n## ")[0]
    assert "Reflectors judging the same pairs" in section
    table = section.split("| world model | reflector |")[1].split("\n\n")[0]
    assert len([line for line in table.splitlines() if line.startswith("| ")]) == 1  # the re-run rewrote its row
    with pytest.raises(ConfigError, match="store_frames=true"):
        evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, f"more_reflectors=[{rid}]", "store_frames=false"))


def test_lerobots_reward_classifier_judges_the_same_stored_pairs(paired, tmp_path):
    """A LeRobot reward classifier (a checkpoint folder) named as a further judge scores the stored
    frames of the pairs beside the reflector, each side's verdict its own score of that frame."""
    import torch

    from hydra.utils import instantiate
    from tests.worldenv_core.models.test_lerobot_reward import CONFIG
    from worldenv_core.models.checkpoint import read_config, save_model

    exp, summary = paired
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    torch.manual_seed(0)
    judge = instantiate(CONFIG).eval()
    reflector = Path(exp, Manifest(exp).latest("train_reflector", task="tiny").files("checkpoint")[0].path).parent
    held_out = read_config(reflector)["meta"]["held_out"]  # trained on what the reflector was: no context seen
    meta = {"kind": "reflector", **rec.config["task"], "camera": "agentview", "eta": 0.5, "held_out": held_out}
    folder = save_model(tmp_path / "lerobot_classifier", judge, CONFIG, meta)
    judged_run = evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, f"more_reflectors=[{folder}]"))
    assert json.dumps(judged_run["headline"]) == json.dumps(summary["headline"])  # the same pairs, not run again
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    pairs = json.loads(next(Path(exp, a.path) for a in rec.files("report") if a.path.endswith("pairs.json")).read_text())
    for r in pairs["sft@1"]["rows"]:
        (more,) = [v for k, v in r["more_reflectors"].items() if "lerobot_classifier" in k]
        assert len(more["imagined_scores"]) == len(r["imagined_scores"]) and all(0 <= x <= 1 for x in more["real_scores"])
    assert any("lerobot_classifier" in name for name in judged_run["judges"])


def test_the_report_shows_the_verdict_table_and_the_real_episode_accounting(paired):
    exp, _ = paired
    report = (Path(exp) / "report" / "report.md").read_text()
    section = report.split("## Verdict fidelity: imagined against real")[1].split("\n## ")[0]
    assert "sft@3" in section and "fidelity_imagined_vs_real.png" in section and "fidelity_verdict_vs_eta.png" in section and "![pair](videos/fidelity_" in section
    assert "![verdict by lever](fidelity_levers.png)" in section and (Path(exp) / "report" / "fidelity_levers.png").exists()
    accounting = report.split("## Real-simulator episodes")[1].split("\n## ")[0]
    assert "| evaluate_imagination |" in accounting and "| collect | scale=tiny, source=expert | training data: expert |" in accounting
    assert "Total: training data: " in accounting and "evaluation: 9" in accounting


def test_a_rerun_reuses_the_pairs_and_bad_settings_fail_first(paired):
    exp, summary = paired
    again = evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, "noise_scales=[1.0]"))
    assert json.dumps(again["headline"]) == json.dumps(summary["headline"])  # sft@1's pairs were kept
    for overrides, match in ((["noise_scales=[0]"], "noise_scales must be positive"),
                             (["horizons=[5]"], "multiples of the chunk"), (["eta=2"], "eta"),
                             (["contexts.init_states=0", "contexts.episodes_per_task=0"], "no contexts"),
                             (["contexts.depth=[0.9,0.5]"], "contexts.depth"), (["rollouts=1"], "rollouts must be at least 2")):
        with pytest.raises(ConfigError, match=match):
            evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, *overrides))


def test_checkpoint_folders_alone_serve_init_state_contexts(paired, tmp_path):
    """Released checkpoints (no manifest, no recorded episode) are enough to measure the verdict
    from the benchmark's init states."""
    exp, _ = paired
    m = Manifest(exp)
    folder = lambda stage: m.resolve(m.latest(stage, task="tiny"), kind="checkpoint")[0].parent  # noqa: E731
    out = evaluate_imagination(stage_cfg(
        "evaluate_imagination", tmp_path / "fresh", *PAIRED, "contexts.episodes_per_task=0", "noise_scales=[1.0]",
        "closed_loop_rollouts=0", f"worldsim_from={folder('train_worldsim')}", f"reflector_from={folder('train_reflector')}",
        f"policies=[{folder('train_policy')}]"))
    assert out["headline"]["rollouts"] == 2 and out["by_context"]["episode"]["rollouts"] == 0
    assert out["real_episodes"] == 2


def test_pairs_on_training_episodes_train_a_reflector_and_count_as_its_training_data(paired):
    """contexts.source=training: the same pairs from a training episode's frames, tagged, kept out of
    the fidelity table, counted as training data; train_reflector trains on both of their sides
    (train.pairs_from), and refuses pairs that start where evaluations judge."""
    from stages.train_reflector.run import run as train_reflector
    from tests.stages.conftest import REFLECTOR

    exp, summary = paired
    m = Manifest(exp)
    held_run = m.latest("evaluate_imagination", task="tiny")
    training = ["contexts.source=training", "contexts.init_states=0", "noise_scales=[1.0]", "closed_loop_rollouts=0",
                "contexts.episode_start=true"]  # its first frame (where LOOP starts) and one mid-episode frame
    with pytest.raises(ConfigError, match="contexts.source=training pairs from mid-episode frames"):
        evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, "contexts.source=training"))
    made = evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, *training))
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    assert rec.tags["contexts"] == "training" and made["headline"]["rollouts"] == 4
    rows = json.loads(next(Path(exp, a.path) for a in rec.files("report") if a.path.endswith("pairs.json")).read_text())
    starts = {r["start"].rsplit("@", 1)[0] for r in rows["sft@1"]["rows"]}
    held = {r["start"].rsplit("@", 1)[0] for r in json.loads(next(
        Path(exp, a.path) for a in held_run.files("report") if a.path.endswith("pairs.json")).read_text())["sft@1"]["rows"]
        if r["context_kind"] == "episode"}
    assert len(starts) == 1 and not starts & held  # the training demo, not the held-out one
    assert sorted(r["start"].rsplit("@", 1)[1] for r in rows["sft@1"]["rows"])[:2] == ["0", "0"]
    report = (Path(exp) / "report" / "report.md").read_text()
    assert f"`{rec.id}`" not in report.split("## Verdict fidelity")[1].split("\n## ")[0]
    accounting = report.split("## Real-simulator episodes")[1].split("\n## ")[0]
    assert "training data: real outcomes labelling imagined rollouts for a reflector | 6 |" in accounting

    metrics = train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR, f"train.pairs_from=[{rec.id}]"))
    assert metrics["paired_episodes"] == 8 and "+ paired rollouts (real labels)" in metrics["training"]
    assert rec.id in Manifest(exp).latest("train_reflector", task="tiny").inputs
    with pytest.raises(ConfigError, match="starts at a benchmark init state"):
        train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR, f"train.pairs_from=[{held_run.id}]"))
    with pytest.raises(ConfigError, match="train.pairs_from with eta_folds"):
        train_reflector(stage_cfg("train_reflector", exp, *[o for o in REFLECTOR if not o.startswith("eta_folds")],
                                  f"train.pairs_from=[{rec.id}]", "eta_folds=2"))
    # train.pairs_eta_every: pairs of every K-th start episode choose eta instead of training (here
    # K = 1: the one training demo's 4 pairs), and the checkpoint carries what they chose
    aside = train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR, f"train.pairs_from=[{rec.id}]",
                                      "train.pairs_eta_every=1"))
    assert aside["paired_episodes"] == 0 and aside["eta_pairs"] == 4
    assert aside["eta_chosen_by"] == "verdict F1 on 4 held-out training pairs"
    ckpt = next(p for p in Manifest(exp).resolve(Manifest(exp).latest("train_reflector", task="tiny"))
                if p.name == "config.json")
    assert json.loads(ckpt.read_text())["meta"]["eta"] == aside["eta"]
    with pytest.raises(ConfigError, match="pairs_eta_every sets pairs aside"):
        train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR, "train.pairs_eta_every=2"))


def test_contexts_lie_at_the_depth_asked_for_in_the_held_out_episodes(paired):
    """contexts.depth: the mid-episode frames spread over that fraction of the part before the first success
    (keyframes a short imagined window can finish from), a run of its own beside the whole-part one. Last in the
    module: the tests above read the latest run as the one with init-state contexts."""
    from worldenv_core.data.mcap_io import read_episode

    exp, _ = paired
    out = evaluate_imagination(stage_cfg("evaluate_imagination", exp, *PAIRED, "contexts.init_states=0",
                                         "contexts.depth=[0.8,0.95]", "noise_scales=[1.0]", "closed_loop_rollouts=0"))
    rec = Manifest(exp).latest("evaluate_imagination", task="tiny")
    rows = json.loads(next(Path(exp, a.path) for a in rec.files("report") if a.path.endswith("pairs.json")).read_text())
    (start,) = {r["start"] for r in rows["sft@1"]["rows"]}
    episode, frame = start.rsplit("@", 1)
    success = np.flatnonzero(read_episode(Path(episode), cameras=[], load_sim_state=False).success)[0]
    assert 0.8 * success <= int(frame) <= 0.95 * success and out["headline"]["rollouts"] == 2
