"""post_train_loop on the tiny task: SFT policy, world simulator and reflector from the manifest,
LOOP iterations in imagination, real-simulator evaluation, resume, and bad settings."""
import json
import pickle
import shutil
import zlib
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from stages.post_train_loop.es_update import export_ledger
from stages.post_train_loop.run import run as post_train_loop
from stages.post_train_loop.training import real_starts
from stages.train_reflector.run import run as train_reflector
from tests.stages.conftest import REFLECTOR, stage_cfg
from worldenv_core.data.mcap_io import read_episode, read_reflector_scores
from worldenv_core.manifest import Manifest
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.rl import es
from worldenv_core.rl.real_rollouts import journal_outcomes
from worldenv_core.stage import ConfigError

pytestmark = [pytest.mark.sim, pytest.mark.slow]
LOOP = ["expert_only=true", "rl.iterations=2", "rl.contexts_per_iteration=1", "rl.n_rollouts=2", "rl.horizon=16",
        "rl.minibatch=2", "eval.every=2", "eval.init_states=1", "eval.workers=1", "progress=false",
        "rl.filter_groups=false"]  # the tiny models' verdicts all agree: every group would be dropped
HORIZON = "task.max_steps=48"  # real evaluations' episodes: the plumbing, not 280 steps of a policy that fails


def cfg(stage, exp, *overrides):
    return stage_cfg(stage, exp, *([HORIZON] if stage in ("post_train_loop", "evaluate") else []), *overrides)


@pytest.fixture(scope="module")
def trained(tiny_models):
    return tiny_models, post_train_loop(cfg("post_train_loop", tiny_models, *LOOP, "eval.paired_contexts=2"))


def test_loop_records_a_post_trained_policy_with_its_real_success_curve(trained, contract):
    exp, metrics = trained
    m = Manifest(exp)
    rec = m.latest("post_train_loop", task="tiny", eta=0.5, n_rollouts=2)  # eta null: the reflector's own 0.5
    used = {m.get(i).stage for i in rec.inputs}
    assert {"train_policy", "train_worldsim", "train_reflector", "collect"} <= used
    files = {p.name: p for p in m.resolve(rec)}
    assert {"model.safetensors", "config.json", "training.png"} <= set(files)
    policy, meta = load_checkpoint(files["model.safetensors"].parent, "policy", contract())
    assert meta["iteration"] == 2 and meta["post_trained_from"]
    assert set(metrics["real_success"]) == {"0", "2"}  # iteration 0 is the SFT policy
    assert all(0.0 <= v <= 1.0 for v in metrics["real_success"].values())
    # and in imagination, on fixed contexts and noise: SFT (0) vs the evaluation points
    assert set(metrics["imagined_reward"]) == set(metrics["imagined_success"]) == {"0", "2"}
    assert all(0.0 <= v <= 1.0 for v in [*metrics["imagined_reward"].values(), *metrics["imagined_success"].values()])
    # beside each real evaluation, the imagined rollouts of the (2) contexts x 2 (scale=tiny) replayed for real: the hack rate
    assert set(metrics["paired_hack_rate"]) == {"0", "2"}
    assert metrics["real_episodes"] == 2 * 1 + 2 * (2 * 2)  # 2 evaluations x (1 init state + 2 x 2 paired replays)
    # a sample of imagined rollouts at iteration 0 and at the evaluation, as MCAP, in the manifest
    imagined = sorted(m.root / f.path for f in rec.files("imagined"))
    assert {p.parent.name for p in imagined} == {"iter_0000", "iter_0002"} and len(imagined) == 8  # 2 x (2 contexts x 2)
    ep = read_episode(imagined[0])
    assert ep.meta.source == "imagined" and ep.meta.extra["iteration"] == "0" and 0 < ep.length <= 16
    assert 0 in read_reflector_scores(imagined[0])
    # the curves in TensorBoard: training per iteration, the evaluations with the imagined-vs-real gap
    acc = EventAccumulator(str(files["training.png"].parent / "tensorboard"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"train/mean_reward", "train/approx_kl", "eval/real_success", "eval/imagined_real_gap"} <= tags
    assert [e.step for e in acc.Scalars("eval/real_success")] == [0, 2]


def test_loop_resumes_and_rejects_bad_settings(trained):
    exp, _ = trained
    post_train_loop(cfg("post_train_loop", exp, *LOOP))  # (finished already if the tests above ran)
    again = post_train_loop(cfg("post_train_loop", exp, *LOOP))  # finished, outputs intact: not run again
    latest = Manifest(exp).latest("post_train_loop")
    assert json.dumps(again, sort_keys=True) == json.dumps(latest.metrics, sort_keys=True) and latest.repeats  # NaN-safe
    shown_otherwise = post_train_loop(cfg("post_train_loop", exp, *LOOP, "eval.imagined_contexts=1", "progress=true"))
    assert shown_otherwise["train_wall_s"] < 5  # evaluation settings do not define the run: same work dir
    with pytest.raises(ConfigError, match="imagined_rollouts must be at least 2"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "eval.imagined_rollouts=1"))
    for override, match in (("rl.n_rollouts=1", "at least 2"), ("eta=1.5", r"eta .* must be in \[0, 1\]"),
                            ("rl.epsilon=0", "epsilon .* must be > 0"), ("rl.target_kl=0", "target_kl must be > 0"),
                            ("rl.verdicts=shuffled", r"rl.verdicts must be one of \['own', 'permuted'\]"),
                            ("policy_collections=every", r"policy_collections must be one of \['latest', 'all'\]")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *LOOP, override))


def test_multirun_sweep_over_eta_on_the_basic_launcher(trained):
    """`-m eta=...` runs one post-training per value, each recorded with its own tags."""
    import subprocess
    import sys

    exp, _ = trained
    overrides = [o for o in LOOP if not o.startswith(("rl.iterations", "eval.every"))]
    cmd = [sys.executable, "-m", "stages.post_train_loop", "-m", "+task=tiny", "scale=tiny", f"experiment_dir={exp}",
           *overrides, "rl.iterations=1", "eval.every=0", "eta=0.3,0.7"]
    done = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[3], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    m = Manifest(exp)
    assert {r.tags["eta"] for r in m.find("post_train_loop", task="tiny", n_rollouts=2)} >= {0.3, 0.7}
    sweep = sorted((Path(exp) / "multirun").glob("post_train_loop-*/*"))
    assert [p.name for p in sweep if p.is_dir()] == ["0_eta0.3_n2", "1_eta0.7_n2"]
    # the sweep's summary beside its runs: one row per point, in eta order, with its plot
    folder = sweep[0].parent
    runs = m.find("post_train_loop", task="tiny", sweep=folder.name)
    assert sorted(r.tags["eta"] for r in runs) == [0.3, 0.7]
    rows = json.loads((folder / "sweep_summary.json").read_text())
    assert [(r["eta"], r["n_rollouts"]) for r in rows] == [(0.3, 2), (0.7, 2)]
    assert all(r["imagined_reward_first"] is not None for r in rows)  # measured before training and at the end
    table = (folder / "sweep_summary.md").read_text()
    assert table.count("\n| 0.") == 2 and (folder / "sweep_summary.png").stat().st_size > 1000


def test_evaluate_the_post_trained_policy_by_name(trained):
    from stages.evaluate.run import run as evaluate

    exp, _ = trained
    out = evaluate(cfg("evaluate", exp, "policy_from=post_trained", "termination=oracle", "init_states=1", "workers=1",
                       "progress=false"))
    rec = Manifest(exp).latest("post_train_loop", task="tiny")
    assert out["policy"].endswith("policy") and str(rec.files("checkpoint")[0].path).split("/")[-2] == "policy"
    assert Manifest(exp).latest("evaluate", task="tiny", policy="post_trained").metrics["episodes"] == 1
    report = (Path(exp) / "report" / "report.md").read_text()  # rebuilt by evaluate: the post-training section
    section = report.split("## Post-training (LOOP in imagination)")[1].split("\n## ")[0]
    assert "| 0.5 | 2 |" in section and " -> " in section  # imagined reward first -> last iterations
    assert "post_training.png" in section and (Path(exp) / "report" / "post_training.png").exists()
    # Table 2: the post-trained policy's world model saw only the expert demos (expert_only above)
    ablation = report.split("## Ablations")[1].split("\n## ")[0]
    row = next(line for line in ablation.splitlines() if line.startswith("| post-trained"))
    assert f"| no (expert demos only) | trained head, eta {rec.tags['eta']} |" in row and row.rstrip().endswith("|  |  |")
    assert f"`post_train_loop/{Path(rec.files('checkpoint')[0].path).parts[-3]}`" in row  # which checkpoint it was
    gifs = sorted((Path(exp) / "report" / "videos").glob("post_trained_oracle_task*.gif"))
    assert len(gifs) == 1 and f"(videos/{gifs[0].name})" in report  # the episode's GIF, beside the report


def test_evaluate_through_the_world_models_view_is_a_diagnostic_apart(trained):
    from stages.evaluate.evaluation import own_suite_evaluations
    from stages.evaluate.run import run as evaluate
    from worldenv_core.report import ReportContext

    exp, _ = trained
    worldsim = Manifest(exp).latest("train_worldsim", task="tiny")
    common = ["policy_from=sft", "termination=oracle", "init_states=1", "workers=1", "progress=false"]
    evaluate(cfg("evaluate", exp, *common))  # the plain view it is paired with
    out = evaluate(cfg("evaluate", exp, *common, f"view_through={worldsim.id}"))
    rec = Manifest(exp).latest("evaluate", task="tiny", view="frames+proprio")
    assert rec.metrics["episodes"] == out["episodes"] == 1
    assert Path(rec.metrics["view_through"]) == (Path(exp) / worldsim.files("checkpoint")[0].path).parent.resolve()
    assert rec.id not in {r.id for r in own_suite_evaluations(ReportContext(Manifest(exp), "tiny", Path(exp) / "report"))}
    report = (Path(exp) / "report" / "report.md").read_text()  # a table of its own, paired with the plain view
    section = report.split("## Shown the real episode as imagination would show it")[1].split("\n## ")[0]
    assert "| frames+proprio |" in section and "| oracle | 1 |" in section
    with pytest.raises(ConfigError, match="view_parts"):
        evaluate(cfg("evaluate", exp, *common, f"view_through={worldsim.id}", "view_parts=[depth]"))


def test_reflector_also_trains_on_the_world_simulators_replays_of_its_episodes(trained):
    """train.with_imagined: each training episode once more as the world simulator imagines it,
    with the real episode's labels; the world model becomes an input and names the run."""
    exp, _ = trained
    m = Manifest(exp)
    real_only = m.latest("train_reflector", task="tiny")
    train_reflector(cfg("train_reflector", exp, *REFLECTOR, "train.with_imagined=true"))
    both = Manifest(exp).latest("train_reflector", task="tiny")
    assert both.id != real_only.id and m.latest("train_worldsim", task="tiny").id in both.inputs
    metas = [load_checkpoint(next(p.parent for p in m.resolve(r) if p.name == "model.safetensors"), "reflector")[1]
             for r in (real_only, both)]
    assert metas[1]["imagined_episodes"] == metas[0]["episodes"] == metas[1]["episodes"] // 2
    assert metas[1]["positive_frames"] == 2 * metas[0]["positive_frames"]  # the imagined copies keep the labels
    assert metas[0]["imagined_episodes"] == 0


def test_the_real_simulator_reference_trains_on_real_rollouts_rewarded_by_the_oracle(trained):
    """env=real: the same LOOP with the real simulator and its oracle; no world model or reflector
    is used, and every rollout is counted as a real episode."""
    exp, _ = trained
    metrics = post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.iterations=1", "eval.every=0",
                                  "rl.filter_groups=true"))
    rec = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    used = {Manifest(exp).get(i).stage for i in rec.inputs}
    assert "train_worldsim" not in used and "train_reflector" not in used and "collect" in used
    assert metrics["train_real_episodes"] == 2  # 1 context x 2 rollouts
    # 16 steps from an episode's start never reach the goal: both rollouts fail, the oracle's reward
    # is 0 for both, the group agrees and is dropped: no PPO step, the policy unchanged
    assert rec.tags["eta"] is None and metrics["final_mean_reward"] == 0.0 and metrics["kept_groups"] == 0.0
    history = json.loads((work := Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).parent)
                         .joinpath("training.json").read_text())
    assert all("approx_kl" not in h for h in history if "mean_reward" in h)
    assert len(list(work.glob("behaviour_*"))) == 1  # the behaviour policy the workers loaded, the latest only
    assert not (work / "rollout_journal").exists()  # kept while an iteration could be cut short, then removed
    with pytest.raises(ConfigError, match="env must be one of"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=simulated"))


def test_the_real_route_from_fresh_placements_with_a_validation_set_and_a_trust_region(trained):
    """rl.contexts=placements: every context a fresh placement (no collected episode needed), the
    fixed validation set measured before training and at each evaluation, the update bounded by
    max_kl, the rollouts' time split recorded; every episode counted by use."""
    exp, _ = trained
    metrics = post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.contexts=placements", "rl.iterations=1",
                                  "eval.every=1", "eval.init_states=0", "eval.validation=2", "rl.max_kl=0.05",
                                  "rl.train_scale_head=false", "rl.group_success=[0.1,0.9]"))
    assert metrics["contexts"] == "fresh placements" and metrics["train_real_episodes"] == 2
    assert set(metrics["validation_success"]) == {"0", "1"} and metrics["real_success"] == {}
    rec = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    history = json.loads(Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).read_text())
    validated = [h for h in history if "validation_success" in h]
    # the validation set at iterations 0 and 1, no benchmark init state; a policy whose weights were validated
    # before (an update the trust region shrank to nothing) is read back from the cache and consumes none
    assert metrics["real_episodes"] == 2 + (0 if validated[-1].get("validation_cached") else 2)
    step = next(h for h in history if "mean_reward" in h)
    assert step["rollout_physics_seconds"] > 0 and step["rollout_render_seconds"] > 0 and "update_seconds" in step
    assert history[0]["validation_episodes"] == 2 and "validation_task0" in history[0]
    # each validated policy is kept in the experiment's cache: the SFT policy at a new run's iteration 0 is read back
    from stages.post_train_loop.evaluation import validation_key, validation_success
    from worldenv_core.stage import task_contract
    work = Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).parent
    cache = work.parent / "validation_cache"
    assert len(list(cache.glob("*.json"))) == (1 if validated[-1].get("validation_cached") else 2)  # a key per weights
    contract = task_contract(cfg("post_train_loop", exp, *LOOP))
    iteration_1 = work / "checkpoints" / "0000001"  # the weights validated at iteration 1
    again = validation_success(str(iteration_1), contract, 2, 1, False, cache=cache)
    assert again["validation_cached"] == 1.0 and again["validation_episodes"] == 0
    assert again["validation_success"] == validated[-1]["validation_success"]
    assert validation_key(str(iteration_1), contract, 3) != validation_key(str(iteration_1), contract, 2)
    for override, match in (("rl.contexts=scenes", r"rl.contexts must be one of \['episodes', 'placements'\]"),
                            ("rl.group_success=[0.9,0.1]", "rl.group_success: .*two fractions"),
                            ("rl.max_kl=0", "max_kl .* must be > 0"), ("rl.optimizer=rmsprop", "rl.optimizer must be"),
                            ("rl.lr_heads=0", "one of them > 0"),
                            ("rl.placement_pool=0", "placement_pool is a number of fixed fresh placements"),
                            ("rl.exploration=episode", "rl.exploration must be one of step, chunk")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.lr_backbone=0", override))
    with pytest.raises(ConfigError, match="placements .* needs env=real"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.contexts=placements"))
    with pytest.raises(ConfigError, match="placement_pool .* with rl.contexts=episodes"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.placement_pool=10"))
    pooled = post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.contexts=placements", "rl.iterations=1",
                                 "eval.every=0", "rl.placement_pool=3", "rl.keep_rollouts=true", "rl.exploration=chunk"))
    assert pooled["contexts"] == 3 and pooled["train_real_episodes"] == 2
    # rl.keep_rollouts: the iteration's rollouts kept beside its behaviour policy, for analysis.critic_probe
    work = Path(next(p for p in Manifest(exp).resolve(Manifest(exp).latest("post_train_loop", task="tiny", env="real"))
                     if p.name == "training.json")).parent
    (kept,) = [p for p in (work / "kept_rollouts").iterdir() if not p.name.endswith("_behaviour")]
    assert len(list(kept.glob("*.rollout"))) == 2 and (kept.parent / f"{kept.name}_behaviour" / "model.safetensors").exists()
    # rl.exploration=chunk reached the real rollouts' jobs (the held draw itself: tests/worldenv_core/models/test_laplace.py)
    key, _ = pickle.loads(zlib.decompress(next(kept.glob("*.rollout")).read_bytes()))
    assert key[-1] == "chunk"
    assert not (work / "rollout_journal").exists()


def test_rollouts_start_part_way_through_the_collected_episodes(trained):
    """rl.mid_episode_frames=n: LOOP's contexts are n recorded frames of each episode before its
    first success, in imagination (the paired replays start there too) and in the real reference."""
    exp, first = trained
    mid = post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.mid_episode_frames=2", "eval.paired_contexts=1"))
    assert mid["contexts"] == 2 * first["contexts"] and mid["dropped_contexts"] == 0
    assert set(mid["paired_hack_rate"]) == set(mid["paired_real_mixed"]) == {"0", "2"}  # replayed from the mid frames
    m = Manifest(exp)
    runs = m.find("post_train_loop", task="tiny", env="imagined")
    work = lambda r: Path(r.files("checkpoint")[0].path).parts[-3]  # noqa: E731
    assert work(runs[-1]) not in {work(r) for r in runs[:-1]}  # a training of its own, not a resume of an earlier run
    real = post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.mid_episode_frames=1", "rl.iterations=1",
                               "eval.every=0"))
    assert real["contexts"] == first["contexts"] and real["train_real_episodes"] == 2
    with pytest.raises(ConfigError, match="mid_episode_frames"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.mid_episode_frames=-1"))
    # keyframes only in the part of each episode asked for (where the verdict is faithful), named in the report
    deep = post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.mid_episode_frames=1",
                               "rl.context_depth=[0.6,1.0]", "rl.iterations=1", "eval.every=0"))
    assert deep["contexts"] == first["contexts"]
    runs = Manifest(exp).find("post_train_loop", task="tiny", env="real")
    assert runs[-1].config["rl"]["context_depth"] == [0.6, 1.0] and work(runs[-1]) != work(runs[-2])
    m = Manifest(exp)
    episodes = [p for p in m.resolve(m.latest("collect", source="expert", task="tiny")) if p.suffix == ".mcap"]
    for start in real_starts(episodes, 1, (0.6, 1.0))[0]:
        ep = read_episode(Path(start.episode), cameras=[])
        before = int(ep.success.argmax()) if ep.success.any() else ep.length
        assert 0.6 * before <= start.frame < before
    for override, match in (("rl.context_depth=[0.6,0.2]", "lo < hi"), ("rl.context_depth=[0.5,1.0]", "mid_episode_frames > 0")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *LOOP, override))


def test_loop_from_a_context_pack_trains_as_the_stage_does_without_episodes_or_encoder(trained, tmp_path):
    """The GPU route, as settings of the stage: `contexts_to=` packs the contexts it would train from
    with their instruction embeddings; `contexts_from=` runs LOOP off them in an experiment with no
    episode (no MCAP, simulator or instruction encoder needed) into the policy the stage trains from
    the same contexts and seed; resumable; a pack of something else is refused."""
    import torch

    from stages.post_train_loop.training import contexts_from_episodes
    from worldenv_core.imagination.context_pack import read_context_pack
    from worldenv_core.models.text import InstructionEncoder

    exp, _ = trained
    settings = [o for o in LOOP if not o.startswith(("expert_only", "eval."))] + ["eval.imagined_contexts=1"]
    stage = post_train_loop(cfg("post_train_loop", exp, "expert_only=true", "eval.every=0", *settings))
    m = Manifest(exp)
    rec = m.latest("post_train_loop", task="tiny", env="imagined")
    inputs = {m.get(i).stage: m.get(i) for i in rec.inputs}
    folder = lambda stage_name: next(p.parent for p in m.resolve(inputs[stage_name])  # noqa: E731
                                     if p.name == "model.safetensors")
    models = [f"policy_from={folder('train_policy')}", f"worldsim_from={folder('train_worldsim')}",
              f"reflector_from={folder('train_reflector')}"]
    records = len(m.records())
    packed = post_train_loop(cfg("post_train_loop", exp, "expert_only=true", *settings, *models,
                                 f"contexts_to={tmp_path / 'contexts.st'}"))
    assert len(Manifest(exp).records()) == records  # an export: no record a later stage could take for a policy
    pack = read_context_pack(tmp_path / "contexts.st")
    episodes = sorted(p for p in m.resolve(inputs["collect"], kind="episodes") if p.suffix == ".mcap")
    want, starts = contexts_from_episodes(episodes, pack.camera)
    assert pack.keys == [st.key for st in starts] and len(pack.contexts) == len(want) == stage["contexts"] == packed["contexts"]
    assert all(torch.equal(a.frame, b.frame) and torch.equal(a.proprio, torch.as_tensor(b.proprio, dtype=torch.float64))
               and a.instruction == b.instruction and a.task_id == b.task_id for a, b in zip(pack.contexts, want))
    text = pack.contexts[0].instruction
    assert torch.allclose(pack.encoder([text]), InstructionEncoder()([text]))
    with pytest.raises(KeyError, match="no embedding"):
        pack.encoder(["open the fridge"])

    gpu = tmp_path / "gpu"  # an experiment with no collection: the pack is all the contexts there are
    there = ["eval.every=0", *settings, *models, f"contexts_from={tmp_path / 'contexts.st'}"]
    post_train_loop(cfg("post_train_loop", gpu, *there))
    g = Manifest(gpu)
    done = g.latest("post_train_loop", task="tiny")
    final = next(p.parent for p in g.resolve(done) if p.name == "model.safetensors")
    tuned, meta = load_checkpoint(final, "policy", None)
    assert meta["trained_from"]["contexts"] == len(pack.contexts) and meta["iteration"] == 2
    assert any(f.kind == "context_pack" for f in done.input_files)
    ours = load_checkpoint(next(p.parent for p in m.resolve(rec) if p.name == "model.safetensors"), "policy", None)[0]
    assert all(torch.allclose(v, ours.state_dict()[k], atol=1e-6) for k, v in tuned.state_dict().items())
    history = json.loads((final.parent / "training.json").read_text())
    assert [h["step"] for h in history if "imagined_success" in h] == [0, 2]
    assert not any("real_success" in h or "validation_success" in h for h in history)  # no simulator there
    weights = (final / "model.safetensors").read_bytes()
    post_train_loop(cfg("post_train_loop", gpu, *there))  # the same command again: finished before, trains nothing
    assert (final / "model.safetensors").read_bytes() == weights
    with pytest.raises(ConfigError, match="not a context pack"):
        post_train_loop(cfg("post_train_loop", tmp_path / "gpu2", *there[:-1],
                            f"contexts_from={folder('train_policy') / 'model.safetensors'}"))
    with pytest.raises(ConfigError, match="mid_episode_frames"):
        post_train_loop(cfg("post_train_loop", tmp_path / "gpu2", *there, "rl.mid_episode_frames=2"))
    with pytest.raises(ConfigError, match="env=imagined"):
        post_train_loop(cfg("post_train_loop", tmp_path / "gpu2", *there, "env=real"))
    work = final.parent

    # measured back here, as a point of a sweep: real success against the starting policy's on the same
    # episodes, and the paired hack rate of both from the evaluate_imagination run that replayed them
    from stages.evaluate.run import run as evaluate
    from stages.evaluate_imagination.run import run as evaluate_imagination
    from analysis import sweep_packs

    real = ["termination=oracle", "init_states=2", "workers=1", "progress=false", "videos_per_task=0"]
    evaluate(cfg("evaluate", exp, f"policy_from={folder('train_policy')}", *real))
    start = m.latest("evaluate", task="tiny").id
    evaluate(cfg("evaluate", exp, f"policy_from={final}", *real))
    evaluate_imagination(cfg("evaluate_imagination", exp, f"policies=[{folder('train_policy')},{final}]",
                             "paired_policies=2", "horizon=16", "contexts.init_states=1", "contexts.episodes_per_task=0",
                             "rollouts=2", "closed_loop_rollouts=0", "gifs=0", "workers=1", "progress=false"))
    sweep_packs.main([str(exp), "--packs", str(work), "--baseline", start, "--out", str(tmp_path / "summary")])
    row, = json.loads((tmp_path / "summary" / "sweep_summary.json").read_text())
    assert (row["eta"], row["n_rollouts"], row["iterations"], row["run"]) == (0.5, 2, 2, work.name)
    assert row["real_episodes"] == m.get(start).metrics["episodes"] and row["real_p"] is not None
    assert row["real_records"] == [m.latest("evaluate", task="tiny").id]
    assert row["real_success_first"] == m.get(start).metrics["success_rate"]
    replayed = m.latest("evaluate_imagination", task="tiny")
    assert row["paired_records"] == [replayed.id]
    per_policy = json.loads(next(m.root / f.path for f in replayed.outputs if f.path.endswith("fidelity.json"))
                            .read_text())["per_policy"]
    said = [per_policy[f"{name}@1"]["hack_rate"] for name in (folder("train_policy"), final)]  # NaN: no imagined success
    assert json.dumps([row["paired_hack_rate_first"], row["paired_hack_rate_last"]]) == json.dumps(said)
    assert row["imagined_reward_first"] == next(h["imagined_reward"] for h in history if "imagined_reward" in h)
    assert (tmp_path / "summary" / "sweep_summary.png").is_file()


def test_the_paired_replay_guard_measures_the_update_and_undoes_one_that_follows_a_hack(trained):
    """rl.guard_contexts: after the update, the policy's imagined rollouts are replayed for real (counted).
    At eta 0 every imagined rollout succeeds at its first check and every real replay of 16 steps fails:
    the hack rate is 1, so a bound of 0.5 undoes the update (what undoing restores, and that an update
    within the bound stays: test_training.py; the tiny models' verdicts all agree, so their updates are zero)."""
    exp, _ = trained
    metrics = post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.iterations=1", "eval.every=0", "eta=0.0",
                                  "rl.guard_contexts=1", "rl.guard_rollouts=2", "rl.guard_max_hack_rate=0.5"))
    assert metrics["guard_hack_rate"] == {"1": 1.0} and metrics["real_episodes"] == 2  # 1 context x 2, replayed
    assert isinstance(metrics["real_episodes"], int)  # a count, though the history keeps the guard's among float stats
    assert metrics["rolled_back"] == 1
    with pytest.raises(ConfigError, match="guard_contexts replays imagined rollouts"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "env=real", "rl.guard_contexts=1"))
    with pytest.raises(ConfigError, match="guard_max_hack_rate must be in"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.guard_contexts=1", "rl.guard_max_hack_rate=2"))


def test_imagination_keyframes_sets_the_peers_contexts_horizon_and_guard_beside_any_recipe():
    """imagination=keyframes (the smoke's route): keyframes part way into the episodes, a bounded horizon and the
    guard, sized by the scale; the recipe still comes from rl=..., and a setting on the command line still wins.
    The default (starts) is the paper's: episode starts to the step limit, no guard."""
    from worldenv_core.stage import compose_config

    def route(*overrides):
        rl = compose_config("post_train_loop", ["+task=tiny", *overrides]).rl
        return rl.mid_episode_frames, list(rl.context_depth), rl.horizon, rl.guard_contexts, rl.guard_rollouts

    assert route("scale=tiny") == (0, [0.0, 1.0], 280, 0, 4)
    assert route("scale=tiny", "imagination=keyframes") == (4, [0.35, 0.7], 64, 1, 2)
    assert route("scale=small", "imagination=keyframes") == (4, [0.35, 0.7], 64, 8, 4)
    assert route("scale=small", "imagination=keyframes", "rl.horizon=32")[2] == 32
    es = compose_config("post_train_loop", ["+task=tiny", "imagination=keyframes", "rl=es_many_pairs"]).rl
    assert (es.policy_update, es.es_pairs, es.contexts, es.guard_contexts, es.horizon) == ("es", 32, "episodes", 8, 64)


def test_filtered_bc_imitates_the_successes_kept_in_the_work_dir(trained):
    """rl.policy_update=filtered_bc: at eta 0 every imagined rollout succeeds, so each iteration's
    rollouts join the buffer (a file per iteration in the work dir, kept after the run) and the
    policy's mean is fitted to all of them; no PPO step is taken. Bad settings are named first."""
    exp, _ = trained
    metrics = post_train_loop(cfg("post_train_loop", exp, *LOOP, "eval.every=0", "eta=0.0",
                                  "rl.policy_update=filtered_bc", "rl.bc_steps=3", "rl.bc_minibatch=2"))
    rec = Manifest(exp).latest("post_train_loop", task="tiny", eta=0.0)
    history = json.loads(Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).read_text())
    steps = [h for h in history if "mean_reward" in h]
    assert [h["buffer_rollouts"] for h in steps] == [2, 4] and all(h["bc_steps"] == 3 for h in steps)
    assert all("ppo_steps" not in h and h["exact_kl"] > 0 for h in steps) and metrics["iterations"] == 2
    work = Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).parent
    assert len(list((work / "success_buffer").glob("*.pt"))) == 2
    for override, match in (("rl.policy_update=dpo", r"rl.policy_update must be one of \['ppo', 'filtered_bc', 'es'\]"),
                            ("rl.bc_steps=0", "rl.bc_steps")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *LOOP, override))


def test_per_chunk_advantages_from_a_critic_fitted_to_the_earlier_iterations(trained):
    """rl.advantages=gae: the first iteration keeps RLOO's advantages and fits the critic, the second
    is weighed per chunk by it (its cross-entropy on the new batch logged before it learns that batch);
    the critic travels in the checkpoint, so a resumed run goes on with it."""
    import torch

    exp, _ = trained
    post_train_loop(cfg("post_train_loop", exp, *LOOP, "eval.every=0", "rl.advantages=gae", "rl.critic_steps=4",
                        "rl.critic_minibatch=4", "rl.critic_hidden=8", "rl.critic_replay=1"))
    rec = Manifest(exp).latest("post_train_loop", task="tiny")
    work = Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).parent
    steps = [h for h in json.loads((work / "training.json").read_text()) if "mean_reward" in h]
    assert [h["critic_fits"] for h in steps] == [0, 1] and "critic_bce" not in steps[0]
    assert steps[1]["critic_bce"] > 0 and steps[1]["critic_bce_constant"] >= 0 and steps[1]["ppo_steps"] >= 1
    state = torch.load(work / "checkpoints" / "0000002" / "training_state.pt", weights_only=False)
    assert state["extra"]["critic"]["fits"] == 2 and state["extra"]["critic"]["feature_dim"] > 0
    assert len(state["extra"]["critic"]["kept"]) == 2  # both iterations' chunks: the replay the next fit would see
    for override, match in (("rl.advantages=td", r"rl.advantages must be one of \['rloo', 'gae'\]"),
                            ("rl.gae_lambda=1.5", r"rl.gae_lambda must be in \[0, 1\]"),
                            ("rl.critic_replay=-1", "rl.critic_replay"),
                            ("rl.policy_update=filtered_bc", "rl.advantages=gae weighs PPO's steps")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.advantages=gae", override))


def test_evolution_strategies_in_weight_space_on_real_and_imagined_rollouts(trained):
    """rl.policy_update=es: antithetic weight-space members act with their mean actions from the same fresh
    placements, every episode counted (or, imagined, from collected episodes' starts in the world model); the step is ARS's, made in the weights the mean reads (the scale head
    untouched), and a resumed run takes the journal's rollouts back. Bad settings are named first."""
    exp, _ = trained
    es_args = [*LOOP, "env=real", "rl=es", "rl.iterations=1", "rl.contexts_per_iteration=2", "rl.es_pairs=2",
               "rl.horizon=16", "eval.every=0", "rl.keep_rollouts=true"]
    metrics = post_train_loop(cfg("post_train_loop", exp, *es_args, f"rl.es_ledger_from={exp}/kept_ledger"))  # none yet
    assert metrics["contexts"] == "fresh placements" and metrics["train_real_episodes"] == 2 * 2 * 2
    rec = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    history = json.loads(Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).read_text())
    step = next(h for h in history if "es_pairs" in h)
    assert step["train_episodes"] == 8 and step["es_pairs"] == 2 and step["rollout_physics_seconds"] > 0
    work = Path(next(p for p in Manifest(exp).resolve(rec) if p.name == "training.json")).parent
    (entry,) = es.read_ledger(work / "es_ledger")  # contexts x members, the seeds, the step's settings
    assert len(entry["success"]) == 2 and len(entry["success"][0]) == 4 and entry["es_sigma"] == 0.05
    (kept,) = [p for p in (work / "kept_rollouts").iterdir() if not p.name.endswith("_behaviour")]
    rollouts = [pickle.loads(zlib.decompress(f.read_bytes())) for f in sorted(kept.glob("*.rollout"))]
    assert len(rollouts) == 8 and all(r["frames"] == [] for _, r in rollouts)  # the outcome only comes back
    assert {key[-2][1] for key, _ in rollouts} == {0.05, -0.05}  # the members, + and - of each direction
    post, meta = load_checkpoint(str(work / "policy"), "policy")
    sft, _ = load_checkpoint(meta["post_trained_from"], "policy")
    moved = {n for (n, a), (_, b) in zip(sft.named_parameters(), post.named_parameters()) if not a.equal(b)}
    assert not any(n.startswith("scale_head.") for n in moved)
    assert bool(moved) == (step["es_return_std"] > 0)  # no step where every member returned the same
    # the campaign's folder (rl.es_ledger_from, none at the start) received the ledger and history after the iteration
    assert es.read_ledger(Path(exp) / "kept_ledger") == [entry] and (Path(exp) / "kept_ledger" / "history.json").exists()
    # a campaign on a machine whose outputs/ is empty: its ledger (kept in the repository) seeds the run, which
    # goes on from the policy the ledger's steps make
    (Path(exp) / "kept_ledger" / "in_progress.json").write_text("[]")  # an older sitting's unfinished iteration
    (finished,) = [p for p in (work / "kept_rollouts").iterdir() if not p.name.endswith("_behaviour")]
    shutil.copytree(finished, work / "rollout_journal" / finished.name)  # as between its step and the next iteration
    kept_ledger = export_ledger(work, Path(exp) / "kept_ledger")
    assert not (kept_ledger / "in_progress.json").exists()  # the run finished its iteration: nothing under way
    shutil.rmtree(work / "rollout_journal" / finished.name)
    seeded = post_train_loop(cfg("post_train_loop", exp, *es_args, "rl.iterations=2", f"rl.es_ledger_from={kept_ledger}"))
    assert seeded["train_real_episodes"] == 16
    rec2 = Manifest(exp).latest("post_train_loop", task="tiny", env="real")
    work2 = Path(next(p for p in Manifest(exp).resolve(rec2) if p.name == "training.json")).parent
    ledger2 = es.read_ledger(work2 / "es_ledger")
    assert work2 != work and len(ledger2) == 2 and ledger2[0] == entry
    assert es.read_ledger(kept_ledger) == ledger2  # the campaign's folder kept up with it
    again = es.replay_ledger(load_checkpoint(meta["post_trained_from"], "policy")[0], ledger2)
    final2, _ = load_checkpoint(str(work2 / "policy"), "policy")
    assert all(p.equal(q) for p, q in zip(again.parameters(), final2.parameters()))
    # a session that ended inside iteration 2: its finished rollouts travel with the ledger (here all 8, each
    # marked by its physics time) and a machine without its outputs/ takes them back instead of running them
    (iter2,) = [p for p in (work2 / "kept_rollouts").iterdir() if not p.name.endswith("_behaviour")]
    records = [{**r, "seconds": {**r["seconds"], "physics": 100.0}} for r in journal_outcomes(iter2.parent)]
    (kept_ledger / "iter_0002.json").unlink()  # the sitting ended before iteration 2's step
    (kept_ledger / "in_progress.json").write_text(json.dumps(records))
    shutil.rmtree(work2)  # the machine is gone
    resumed = post_train_loop(cfg("post_train_loop", exp, *es_args, "rl.iterations=2", f"rl.es_ledger_from={kept_ledger}"))
    step2 = [h for h in json.loads((work2 / "training.json").read_text()) if "es_pairs" in h][-1]
    assert len(records) == 8 and step2["rollout_physics_seconds"] == 800.0 and resumed["iterations"] == 2
    assert es.read_ledger(work2 / "es_ledger") == ledger2  # the same outcomes, the same step
    # ... and inside its first iteration, before any ledger entry: the rollouts alone seed the run
    first = Path(exp) / "first_sitting"
    first.mkdir()
    records = [{**r, "seconds": {**r["seconds"], "physics": 100.0}} for r in journal_outcomes(work / "kept_rollouts")]
    (first / "in_progress.json").write_text(json.dumps(records))
    shutil.rmtree(work)
    post_train_loop(cfg("post_train_loop", exp, *es_args, f"rl.es_ledger_from={first}"))
    step1 = next(h for h in json.loads((work / "training.json").read_text()) if "es_pairs" in h)
    assert len(records) == 8 and step1["rollout_physics_seconds"] == 800.0 and es.read_ledger(work / "es_ledger") == [entry]
    with pytest.raises(ConfigError, match="was made with rl.es_sigma=0.05"):
        post_train_loop(cfg("post_train_loop", exp, *es_args, "rl.iterations=3", "rl.es_sigma=0.1",
                            f"rl.es_ledger_from={kept_ledger}"))
    # the folder names the weights its steps were made on; on another starting policy they would make another policy
    assert json.loads((kept_ledger / "start.json").read_text())["weights"] == es.weights_digest(sft)
    (kept_ledger / "start.json").write_text(json.dumps({"weights": "0123456789abcdef"}))  # a retrained SFT's ledger
    with pytest.raises(ConfigError, match="made on starting weights 0123456789abcdef"):
        post_train_loop(cfg("post_train_loop", exp, *es_args, "rl.iterations=3", f"rl.es_ledger_from={kept_ledger}"))
    for override, match in (("rl.es_sigma=0", r"rl.es_sigma must be > 0"), ("rl.es_top=3", "rl.es_top must be"),
                            ("rl.es_discount=1.5", r"rl.es_discount must be in \(0, 1\]"),
                            ("rl.es_parameters=all", "rl.es_parameters must be one of"),
                            ("rl.task_focus=2", r"rl.task_focus must be null \(every task\) or an int in 1..1"),
                            ("rl.es_min_mixed=-1", "rl.es_min_mixed"),
                            ("rl.es_return=reward", "rl.es_return must be one of"),
                            ("rl.es_return=score", "rl.es_return=score needs env=imagined")):
        with pytest.raises(ConfigError, match=match):
            post_train_loop(cfg("post_train_loop", exp, *es_args, override))
    # the imagined route: the members' rollouts as one batch through the world model, the reflector's verdict
    # as success, no real episode spent on training
    imagined = post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl.policy_update=es", "rl.iterations=1",
                                   "rl.es_pairs=2", "rl.contexts_per_iteration=2", "eval.every=0", "rl.task_focus=1"))
    assert imagined["train_real_episodes"] == 0 and imagined["iterations"] == 1
    rec3 = Manifest(exp).latest("post_train_loop", task="tiny", env="imagined")
    work3 = Path(next(p for p in Manifest(exp).resolve(rec3) if p.name == "training.json")).parent
    (entry3,) = es.read_ledger(work3 / "es_ledger")
    assert len(entry3["success"]) == 2 and len(entry3["success"][0]) == 4
    step3 = next(h for h in json.loads((work3 / "training.json").read_text()) if "es_pairs" in h)
    assert step3["train_episodes"] == 0 and step3["rollout_imagination_seconds"] > 0
    with pytest.raises(ConfigError, match="rl.contexts=placements draws fresh scenes in the real simulator"):
        post_train_loop(cfg("post_train_loop", exp, *LOOP, "rl=es"))


def test_the_post_trained_policys_rollouts_collect_into_a_folder_named_by_that_policy(trained):
    """A refit round collects the post-trained policy's rollouts: `policy_from=post_trained` names the checkpoint it
    resolved to in the folder, so a later round (another post-trained policy) never resumes into this one."""
    from stages.collect.episodes import episode_dir
    from stages.collect.run import run as collect

    exp, _ = trained
    rollouts = ["source=policy", "episodes_per_task=1", "workers=1", "progress=false", "lerobot_export=false",
                "task.max_steps=16"]
    out = collect(cfg("collect", exp, *rollouts, "policy_from=post_trained"))
    m = Manifest(exp)
    post = m.latest("post_train_loop", task="tiny")
    assert post.id in m.latest("collect", task="tiny", source="policy").inputs and out["collection"]["kept"] == 1
    checkpoint = Path(m.resolve(post)[0]).parent.resolve().relative_to(m.root).as_posix()
    assert out["collection"]["episode_dir"] == str(episode_dir(cfg("collect", exp, *rollouts, f"policy_from={checkpoint}")))
    assert out["collection"]["episode_dir"] != str(episode_dir(cfg("collect", exp, *rollouts, "policy_from=post_trained")))
