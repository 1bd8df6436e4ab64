"""The experiment report is the sum of the stages' sections: each section renders from manifest
records alone (tags, metrics and the reports a run wrote), and `write_report` assembles them in
pipeline order. Records here are written by hand, as the stages write them."""
import json

from stages.collect import evaluation as collect
from stages.evaluate import evaluation as evaluate
from stages.evaluate_imagination import evaluation as evaluate_imagination
from stages.post_train_loop import evaluation as post_train_loop
from stages.report import SECTIONS, wall_time_section, write_report
from stages.train_reflector import evaluation as train_reflector
from stages.train_worldsim import evaluation as train_worldsim
from worldenv_core.manifest import Manifest, StageRun
from worldenv_core.report import ReportContext, markdown_table

TAGS = {"task": "tiny", "scale": "tiny"}


def _write(path, data) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def _experiment(root):
    """One record per stage, each with the files its section reads."""
    m = Manifest(root)
    with StageRun(m, "collect", {**TAGS, "source": "policy"}, {}) as s:
        for i in range(3):
            s.add_output(_write(root / "data" / f"ep{i}.mcap", f"episode {i}"), kind="episodes")
        s.metrics["collection"] = {"kept_frames": 120, "success_rate": 1 / 3}
        s.metrics["real_episodes"] = 3
    collected = m.latest("collect")
    with StageRun(m, "train_worldsim", {**TAGS, "data": "expert+policy"}, {}) as s:
        s.use(collected, kind="episodes")
        v = {"model_psnr": 25.0, "copy_psnr": 22.0, "model_ssim": 0.8, "copy_ssim": 0.7, "plain_ssim": 0.75}
        s.add_output(_write(root / "ws" / "fidelity.json", {"fidelity": {"8": v}}), kind="report")
    with StageRun(m, "train_reflector", {**TAGS, "data": "expert+policy", "hard_negatives": "mined"}, {}) as s:
        s.record.tags["reward"] = "VLM yes/no"
        s.metrics["training"] = "10 steps, label delay 0, mining every 5 > 0.3"
        per_step = {"accuracy": 0.9, "f1": 0.8, "auroc": 0.95}
        s.add_output(_write(root / "rf" / "reflector_eval.json", {
            "eta": 0.5, "held_out_episodes": 4,
            "real": {"per_step": per_step, "termination": {"all": {"f1": 0.75}}}}), kind="report")
    with StageRun(m, "post_train_loop", {**TAGS, "eta": 0.5, "n_rollouts": 4}, {}) as s:
        for stage in ("train_worldsim", "train_reflector"):
            s.inputs.append(m.latest(stage).id)
        history = [{"step": 0, "real_success": 0.2}, {"step": 1, "mean_reward": 0.3}, {"step": 2, "mean_reward": 0.5,
                                                                                       "real_success": 0.4}]
        _write(root / "loop" / "training.json", history)
        s.add_output(_write(root / "loop" / "training.png", "png"), kind="plot")
        s.metrics.update(iterations=2, real_success={"0": 0.2, "2": 0.4}, imagined_reward={"0": 0.1, "2": 0.3},
                         imagined_success={"0": 0.0, "2": 0.5})
    loop = m.latest("post_train_loop")
    for policy, success in (("sft", [True, False]), ("post_trained", [True, True])):
        # each evaluation its own run (its own config), as two policies' evaluations are: with one config and
        # a start in the same second they would read as one termination=all pass and be timed once
        with StageRun(m, "evaluate", {**TAGS, "termination": "oracle", "policy": policy},
                      {"policy_from": policy}) as s:
            if policy == "post_trained":
                s.inputs.append(loop.id)
            rows = [{"task_id": 0, "init_state": i, "success": ok} for i, ok in enumerate(success)]
            summary = {"policy": f"/x/{policy}/run/policy", "termination": "oracle", "init_states": 2,
                       "success_rate": sum(success) / 2, "suite": "libero_object",
                       "per_task": [{"task_id": 0, "task": "pick", "success_rate": sum(success) / 2}]}
            s.add_output(_write(root / "ev" / policy / "results.json", summary), kind="report")
            s.add_output(_write(root / "ev" / policy / "episodes.json", rows), kind="report")
            s.metrics["real_episodes"] = 2
    with StageRun(m, "evaluate_imagination", {**TAGS, "eta": 0.5, "sampling_steps": None, "worldsim": "w1",
                                              "reflector": "r1"}, {}) as s:
        row = {"task_id": 0, "context_kind": "init", "chunk": 8, "steps": 16, "real_error": None,
               "frames": {"8": [20.0, 0.6]}, "copy": {"8": [18.0, 0.5]}}
        # a hit (stops at 8, real success at 8), a hack, a miss, an agreed failure
        verdicts = (([0, 0.9, 0.9], 8), ([0, 0.7, 0.7], None), ([0, 0.3, 0.3], 12), ([0, 0.1, 0.1], None))
        rows = [{**row, "context": i, "imagined_scores": sc, "real_scores": [0, 0.2, 0.2], "real_first_success": first}
                for i, (sc, first) in enumerate(verdicts)]
        results = {"sft@1": {"rows": rows, "closed_loop": [True, False], "imagined_rollouts": 4, "real_episodes": 6},
                   "sft@3": {"rows": rows[:2], "closed_loop": [False, False], "imagined_rollouts": 2, "real_episodes": 4}}
        summary = evaluate_imagination.summarise(results, ["sft@1", "sft@3"], 0.5, [8])
        s.add_output(_write(root / "fi" / "fidelity.json", summary), kind="report")
        s.metrics["real_episodes"] = summary["real_episodes"]
    return m


def test_each_stage_renders_its_own_section(tmp_path):
    ctx = ReportContext(_experiment(tmp_path), "tiny", tmp_path / "report")
    ctx.out.mkdir()
    text = "\n".join(evaluate.section(ctx))
    assert "## Success in the real simulator" in text and "| **all** | **50.0 %** | **100.0 %** |" in text
    assert "exact McNemar p = 1." in text and (ctx.out / "success.png").exists()
    assert "## Ablations" in text and "VLM yes/no, eta 0.5" in text  # the reward kind is the reflector's tag
    text = "\n".join(post_train_loop.section(ctx))
    assert "| 0.5 | 4 | 2 | expert+policy | expert+policy |" in text and "0: 20 %, 2: 40 %" in text
    assert (ctx.out / "post_training.png").exists()
    text = "\n".join(train_worldsim.section(ctx))
    assert "| expert+policy | 8 | 25.00 | 22.00 | 0.800 | 0.700 | 0.750 |" in text
    text = "\n".join(train_reflector.section(ctx))
    assert "VLM yes/no | 10 steps, label delay 0, mining every 5 > 0.3 | 0.5 | 4 | real | 0.900" in text
    text = "\n".join(collect.section(ctx))
    assert "| policy | tiny | 3 | 120 | 33 % |" in text
    text = "\n".join(evaluate_imagination.section(ctx))  # pairs: hit, hack, miss, agreed failure
    # with each figure its 95 % interval over the 4 contexts (one rollout each: as wide as it gets)
    assert ("| w1 | r1 | 0.50 | default, default | sft@1 | 4 | 0.750 (target >= 0.9) [0.00, 1.00] | "
            "0.500 (target >= 0.8) [0.00, 1.00] | 50.0 % (target <= 0.1) |") in text
    assert "| 50.0 % / 50.0 % | 0.0 % (met) | 0 | 0.000 / 0.000 |" in text and "| sft@3 | 100.0 % |  | 50.0 % | 0.0 % |" in text


def test_the_report_is_the_sections_in_order_then_wall_time(tmp_path):
    m = _experiment(tmp_path)
    text = write_report(tmp_path, "tiny").read_text()
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    assert headings == ["## Success in the real simulator", "## Ablations (the paper's Table 2, as far as run)",
                        "## Verdict fidelity: imagined against real", "## Post-training (LOOP in imagination)", "## World simulator (open loop on held-out episodes)",
                        "## Reflector (held-out episodes, newest first)", "## Data (newest collection of each source)",
                        "## Real-simulator episodes", "## Wall time per stage"]
    accounting = text.split("## Real-simulator episodes")[1].split("\n## ")[0]
    assert "| collect | scale=tiny, source=policy | training data: policy | 3 |" in accounting
    assert "| evaluate_imagination | eta=0.5, sampling_steps=None, scale=tiny | evaluation (paired replay) | 10 |" in accounting
    assert "Total: training data: 3, evaluation: 14." in accounting
    wall = text.split("## Wall time per stage")[1]
    total = sum(r.wall_time_s for r in m.records())  # every record here is its stage's newest, each its own run
    assert f"Total: {total:.0f} s (0 h 00 min)" in wall
    records = m.records()
    for r in records:  # as if each had run for an hour, the two evaluations in one pass (same config and start)
        r.wall_time_s = 3600.0
        if r.stage == "evaluate":
            r.config_hash, r.started = "one pass", "t0"
    wall = "\n".join(wall_time_section(ReportContext(m, "tiny", tmp_path / "report", records)))
    assert f"Total: {3600 * (len(records) - 1)} s ({len(records) - 1} h 00 min)" in wall
    ctx = ReportContext(m, "tiny", tmp_path / "report")
    for section in SECTIONS:  # every section's lines appear as it renders them
        assert "\n".join(section(ctx)) in text


def test_the_real_simulator_reference_is_plotted_beside_the_imagined_route_and_its_episodes_counted(tmp_path):
    from stages.report import real_episodes_section

    m = _experiment(tmp_path)
    with StageRun(m, "post_train_loop", {**TAGS, "eta": None, "n_rollouts": 4, "env": "real"}, {}) as s:
        s.inputs.append(m.latest("collect").id)  # its contexts: 3 real episodes collected
        _write(tmp_path / "real" / "training.json", [{"step": 0, "real_success": 0.2}, {"step": 1, "mean_reward": 0.5}])
        s.add_output(_write(tmp_path / "real" / "training.png", "png"), kind="plot")
        s.metrics.update(iterations=2, real_success={"0": 0.2, "2": 0.6}, train_real_episodes=16)
    ctx = ReportContext(m, "tiny", tmp_path / "report")
    ctx.out.mkdir()
    real, imagined = m.latest("post_train_loop", env="real"), m.find("post_train_loop")[0]
    assert post_train_loop.real_episodes_used(ctx, real) == (3, 8)  # + 8 per iteration of its own
    assert post_train_loop.real_episodes_used(ctx, imagined) == (0, 0)
    text = "\n".join(post_train_loop.section(ctx))
    assert "| real | None | 4 | 2 | none | oracle |" in text and "| imagined | 0.5 | 4 | 2 |" in text
    assert "| 0: 20 %, 2: 60 % |" in text  # by iteration, in order
    assert "![imagined vs real route](routes.png)" in text and (ctx.out / "routes.png").stat().st_size > 1000
    accounting = "\n".join(real_episodes_section(ctx))
    assert "| training rollouts (the real-simulator reference) | 16 |" in accounting
    assert "Total: training data: 19, evaluation: 14." in accounting


def test_the_newest_sweep_over_eta_and_n_is_summarised(tmp_path):
    m = Manifest(tmp_path)
    for sweep, eta, n, last in (("old", 0.5, 4, 0.9), ("new", 0.7, 8, 0.3), ("new", 0.3, 8, 0.5), ("new", 0.3, 4, 0.4)):
        with StageRun(m, "post_train_loop", {**TAGS, "eta": eta, "n_rollouts": n, "env": "imagined", "sweep": sweep}, {}) as s:
            s.metrics.update(iterations=2, real_success={"0": 0.2, "2": last}, imagined_reward={"0": 0.1, "2": 0.3},
                             imagined_success={"0": 0.0, "2": 0.5},
                             paired_hack_rate={"0": 0.5, "2": 0.25}, kept_groups=0.5)
    ctx = ReportContext(m, "tiny", tmp_path / "report")
    ctx.out.mkdir()
    text = "\n".join(post_train_loop.section(ctx))
    sweep = text.split("Sweep `new`")[1]
    rows = [line for line in sweep.splitlines() if line.startswith("| 0.")]
    assert rows == [  # by N, then eta; SFT -> last
        f"| 0.3 | 4 | 2 | 20.0 % -> 40.0 % | 0.100 -> 0.300 | 50.0 % -> 25.0 % | 50.0 % | `{m.find('post_train_loop')[3].id}` |",
        f"| 0.3 | 8 | 2 | 20.0 % -> 50.0 % | 0.100 -> 0.300 | 50.0 % -> 25.0 % | 50.0 % | `{m.find('post_train_loop')[2].id}` |",
        f"| 0.7 | 8 | 2 | 20.0 % -> 30.0 % | 0.100 -> 0.300 | 50.0 % -> 25.0 % | 50.0 % | `{m.find('post_train_loop')[1].id}` |"]
    assert "90.0 %" not in sweep and (ctx.out / "sweep.png").exists()


def test_sections_are_empty_on_an_experiment_without_their_stage(tmp_path):
    ctx = ReportContext(Manifest(tmp_path), "tiny", tmp_path)
    assert [s(ctx) for s in SECTIONS[1:]] == [[], [], [], [], []]
    assert "No evaluation yet" in "\n".join(evaluate.section(ctx))


def test_markdown_table():
    assert markdown_table(["a", "b"], [[1, "x"]]) == ["| a | b |", "|---|---|", "| 1 | x |"]
