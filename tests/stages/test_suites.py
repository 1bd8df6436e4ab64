"""The cross-suite table reads each suite's experiment: SFT against post-trained with the paired test."""
import json

from stages.suites import main, suite_row
from tests.stages.test_report import _experiment


def test_each_suite_row_pairs_sft_and_post_trained_on_the_episodes_both_ran(tmp_path):
    _experiment(tmp_path / "a")  # oracle: SFT solves 1 of 2 init states, the post-trained policy both
    row = suite_row(tmp_path / "a", "tiny")
    assert row["oracle"] == {"sft": 0.5, "post_trained": 1.0, "episodes": 2, "only_a": 0, "only_b": 1, "p_value": 1.0}
    assert "fixed" not in row  # not evaluated with that termination
    (tmp_path / "b").mkdir()
    main([str(tmp_path / "out"), f"tiny={tmp_path / 'a'}", f"other={tmp_path / 'b'}"])
    text = (tmp_path / "out" / "suites.md").read_text()
    assert "| tiny | 50.0 % -> 100.0 % | +50.0 | 0 / 1 | 1 | 2 |  |  |" in text
    assert "| other | not run |" in text
    assert [r["task"] for r in json.loads((tmp_path / "out" / "suites.json").read_text())] == ["tiny", "other"]


def test_which_limit_holds_is_read_off_the_verdict_the_loop_and_the_real_reference(tmp_path):
    """Where post-training does not gain, each suite's row says which limit its own records show."""
    from stages.suites import limits
    from worldenv_core.manifest import Manifest, StageRun

    m = _experiment(tmp_path / "a")  # its LOOP raised imagined success 0 -> 50 %
    with StageRun(m, "evaluate_imagination", {"task": "tiny", "scale": "tiny", "eta": 0.5}, {}) as s:
        s.metrics["headline"] = {"auroc": 0.75, "f1": 0.5, "hack_rate": 0.5, "imagined_success": 0.5,
                                 "real_success": 0.25, "rollouts": 4}
    with StageRun(m, "evaluate_imagination", {"task": "tiny", "scale": "tiny", "eta": 0.5, "contexts": "training"},
                  {}) as s:  # pairs made to train a reflector on: not the verdict on held-out contexts
        s.metrics["headline"] = {"auroc": 1.0, "f1": 1.0, "hack_rate": 0.0, "imagined_success": 0.5,
                                 "real_success": 0.5, "rollouts": 4}
    with StageRun(m, "post_train_loop", {"task": "tiny", "scale": "tiny", "env": "real"}, {}) as s:
        s.metrics["real_success"] = {"0": 0.3, "10": 0.3}
    got = limits(tmp_path / "a", "tiny")
    assert got["verdict"]["hack_rate"] == 0.5 and got["loop"]["imagined_success"] == (0.0, 0.5)
    assert got["reference"]["real_success"] == (0.3, 0.3)
    assert got["holds"] == ["verdict fidelity (auroc, f1, hack_rate off target)",
                            "world-model drift (imagined - real +25 points)",
                            "RL capacity (no real gain with the real simulator as environment)"]
    assert Manifest(tmp_path / "a").latest("evaluate_imagination").tags.get("contexts") == "training"
    (tmp_path / "b").mkdir()
    main([str(tmp_path / "out"), f"tiny={tmp_path / 'a'}", f"other={tmp_path / 'b'}"])
    text = (tmp_path / "out" / "suites.md").read_text().split("## Which limit holds")[1]
    assert ("| tiny | 0.75 / 0.50 / 50.0 % (4) | 50.0 % / 25.0 % | 0.0 % -> 50.0 % | 30.0 % -> 30.0 % | verdict "
            "fidelity (auroc, f1, hack_rate off target); world-model drift") in text
    assert "| other | not measured |  |  | not run | none measured |" in text
    assert limits(tmp_path / "b", "tiny") == {"holds": []}


def _kept_evaluation(root, suite, name, policy, termination, outcomes):
    """An evaluation folder as `analysis.keep` leaves it: {(task, init state): success}."""
    folder = root / suite / name
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({"policy": policy, "termination": termination, "suite": suite,
                                                     "success_rate": sum(outcomes.values()) / len(outcomes)}))
    (folder / "episodes.json").write_text(json.dumps([{"task_id": t, "init_state": i, "success": s}
                                                      for (t, i), s in outcomes.items()]))


def test_the_kept_table_pools_each_sides_folders_and_pairs_them_by_episode(tmp_path):
    """`--kept`: the table from evaluations kept in the repository, no experiment directory."""
    from stages.suites import kept_rows

    _kept_evaluation(tmp_path, "libero_goal", "evaluate-s1", "checkpoints/g/sft", "oracle", {(0, 0): True, (0, 1): False})
    _kept_evaluation(tmp_path, "libero_goal", "evaluate-s2", "checkpoints/g/sft", "oracle", {(1, 2): False, (1, 3): False})
    _kept_evaluation(tmp_path, "libero_goal", "evaluate-p1", "post/policy", "oracle",
                     {(0, 0): True, (0, 1): True, (1, 2): True, (1, 3): True, (1, 4): True})  # (1, 4): unpaired
    fidelity = {"headline_policy": "sft@1", "headline": {"rollouts": 8, "imagined_success": 0.5, "real_success": 0.0,
                                                         "hack_rate": 1.0, "auroc": float("nan"), "f1": 0.0}}
    (tmp_path / "libero_goal" / "evaluate_imagination-v").mkdir()
    (tmp_path / "libero_goal" / "evaluate_imagination-v" / "fidelity.json").write_text(json.dumps(fidelity))
    spec = tmp_path / "suites.yaml"
    spec.write_text(
        "rows:\n- suite: libero_goal\n  sft: {policy: SFT, oracle: [evaluate-s1, evaluate-s2]}\n"
        "  post_trained: {policy: LOOP, oracle: [evaluate-p1]}\n  note: n\n"
        "verdicts:\n- {suite: libero_goal, run: evaluate_imagination-v, contexts: starts}\n")
    rows, verdicts = kept_rows(spec)
    assert rows[0]["oracle"] == {"sft": 0.25, "post_trained": 1.0, "episodes": 4, "only_a": 0, "only_b": 3,
                                 "p_value": 0.25}
    assert "fixed" not in rows[0]
    # a NaN AUROC (no real success among the pairs) is unmeasured, not off target
    assert verdicts[0]["holds"] == ["verdict fidelity (f1, hack_rate off target)",
                                    "world-model drift (imagined - real +50 points)"]
    main(["--kept", str(spec)])
    text = (tmp_path / "suites.md").read_text()
    assert "| libero_goal | SFT | LOOP | 25.0 % -> 100.0 % | +75.0 | 0 / 3 | 0.25 | 4 |  |  | n |" in text
    assert "| libero_goal | sft@1 | starts | 8 | 50.0 % | 0.0 % | 100.0 % |" in text


def test_the_kept_spec_is_checked_before_anything_is_read(tmp_path):
    import pytest

    from stages.suites import kept_rows
    from worldenv_core.errors import ConfigError

    _kept_evaluation(tmp_path, "libero_goal", "evaluate-s1", "sft", "oracle", {(0, 0): True})
    _kept_evaluation(tmp_path, "libero_goal", "evaluate-f1", "post", "fixed", {(0, 0): True})
    spec = tmp_path / "suites.yaml"
    spec.write_text("rows:\n- suite: libero_goal\n  sft: {policy: S, oracle: [evaluate-s1]}\n"
                    "  post_trained: {policy: P, oracle: [evaluate-gone]}\n")
    with pytest.raises(ConfigError, match="evaluate-gone has no episodes.json"):
        kept_rows(spec)
    spec.write_text("rows:\n- suite: libero_goal\n  sft: {policy: S, oracle: [evaluate-s1]}\n"
                    "  post_trained: {policy: P, oracle: [evaluate-f1]}\n")
    with pytest.raises(ConfigError, match="post_trained oracle: the evaluations ran libero_goal with fixed"):
        kept_rows(spec)
    with pytest.raises(ConfigError, match="no such file"):
        kept_rows(tmp_path / "missing.yaml")


def test_the_repositorys_kept_table_is_what_its_spec_generates(tmp_path):
    """results/suites.md is generated: regenerating it from results/suites.yaml changes nothing."""
    from pathlib import Path

    from stages.suites import write_kept

    repo = Path(__file__).resolve().parents[2]
    write_kept(repo / "results" / "suites.yaml", tmp_path)
    assert (tmp_path / "suites.md").read_text() == (repo / "results" / "suites.md").read_text()


def test_a_kept_verdict_drops_the_pairs_whose_real_side_belonged_to_another_tasks_start(tmp_path):
    """Pairs made before a benchmark init state's start named its task ('init0' in two tasks) have another
    task's replays as their real side: the kept table recomputes the verdict without them and says so."""
    from stages.suites import kept_rows

    def row(task, kind, start, imagined, real_first):
        return {"task_id": task, "context": 0, "context_kind": kind, "start": start, "chunk": 8, "steps": 32,
                "imagined_scores": [0.0, imagined], "real_scores": [0.0, 0.0], "real_first_success": real_first,
                "real_error": None}

    rows = [row(0, "init", "init0", 0.9, None), row(1, "init", "init0", 0.9, None),  # void: one start, two tasks
            row(0, "episode", "d/a.mcap@5", 0.9, 3), row(1, "episode", "d/b.mcap@5", 0.1, 3)]
    folder = tmp_path / "libero_goal" / "evaluate_imagination-v"
    folder.mkdir(parents=True)
    (folder / "fidelity.json").write_text(json.dumps({"headline_policy": "p", "eta": 0.5, "headline": {
        "rollouts": 4, "imagined_success": 0.75, "real_success": 0.5, "hack_rate": 0.67}}))
    (folder / "pairs.json").write_text(json.dumps({"p": {"rows": rows}}))
    spec = tmp_path / "suites.yaml"
    spec.write_text("verdicts:\n- {suite: libero_goal, run: evaluate_imagination-v, contexts: starts}\n")
    (v,) = kept_rows(spec)[1]
    assert v["rollouts"] == 2 and v["imagined_success"] == 0.5 and v["real_success"] == 1.0 and v["hack_rate"] == 0.0
    assert "2 of 4 pairs void" in v["contexts"] and v["closed_loop_success"] is None
    # a run whose init states each served one task (or named their task) keeps every pair
    for r, start in zip(rows[:2], ("task0/init0", "task1/init0")):
        r["start"] = start
    (folder / "pairs.json").write_text(json.dumps({"p": {"rows": rows}}))
    (v,) = kept_rows(spec)[1]
    assert v["rollouts"] == 4 and v["contexts"] == "starts"
