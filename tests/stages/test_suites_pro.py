"""The perturbed-suite table: each release's SFT and post-trained policies paired per perturbed suite,
from experiments or from the evaluations kept in the repository."""
import json

import pytest

from stages.suites_pro import main as suites_pro
from tests.stages.test_report import _experiment


def _evaluations(experiment, runs):
    """Oracle evaluations of the tiny task recorded in `experiment`'s manifest: (policy, evaluated suite) -> the
    successes of init states 0, 1, ..."""
    from worldenv_core.manifest import Manifest, StageRun

    m = Manifest(experiment)
    for (policy, suite), success in runs.items():
        with StageRun(m, "evaluate", {"task": "tiny", "scale": "tiny", "termination": "oracle", "policy": policy,
                                      "eval_suite": suite}, {}) as s:
            folder = experiment / "pro" / policy / suite
            folder.mkdir(parents=True)
            (folder / "results.json").write_text(json.dumps({"suite": suite, "max_steps": 280,
                                                             "success_rate": sum(success) / len(success)}))
            (folder / "episodes.json").write_text(json.dumps([{"task_id": 0, "init_state": i, "success": ok}
                                                              for i, ok in enumerate(success)]))
            s.add_output(folder / "results.json", kind="report")
            s.add_output(folder / "episodes.json", kind="report")


def test_the_perturbed_suite_table_pairs_each_perturbation_beside_the_own_suite(tmp_path):
    """`--perturbed`: per suite evaluated on, SFT and post-trained paired by episode; a policy not
    evaluated there (not released) leaves its cell so named, and the own suite comes first."""

    _experiment(tmp_path / "a")  # own suite: SFT 1 of 2, post-trained 2 of 2
    _evaluations(tmp_path / "a", {("sft", "libero_object_swap"): [True, True, False, False],
                                  ("post_trained", "libero_object_swap"): [True, True, True, True],
                                  ("sft", "libero_object_lan"): [False, True, False, False]})
    suites_pro([str(tmp_path / "out"), f"tiny={tmp_path / 'a'}"])
    rows = json.loads((tmp_path / "out" / "suites_pro.json").read_text())
    assert [(r["suite"], r["perturbation"]) for r in rows] == [("libero_object", "none"), ("libero_object_lan", "lan"),
                                                               ("libero_object_swap", "swap")]
    assert rows[2]["paired"] == {"sft": 0.5, "post_trained": 1.0, "episodes": 4, "only_a": 0, "only_b": 2, "p_value": 0.5}
    text = (tmp_path / "out" / "suites_pro.md").read_text()
    assert "| tiny | the project's | libero_object_lan | lan | 280 | 25.0 % (4) | not released |  |  |  |" in text
    assert "| tiny | the project's | libero_object_swap | swap | 280 | 50.0 % (4) | 100.0 % (4) | +50.0 | 0 / 2 | 0.5 |" in text
    # another release of the same suite (`<task>:<label>`), its rows after the first's and named by its label
    suites_pro([str(tmp_path / "out"), f"tiny={tmp_path / 'a'}", f"tiny:ACT={tmp_path / 'a'}"])
    rows = json.loads((tmp_path / "out" / "suites_pro.json").read_text())
    assert [r["release"] for r in rows] == ["the project's"] * 3 + ["ACT"] * 3
    assert "| tiny | ACT | libero_object_swap | swap | 280 | 50.0 % (4) | 100.0 % (4) | +50.0 | 0 / 2 | 0.5 |" in (
        tmp_path / "out" / "suites_pro.md").read_text()
    # a release post-trained from the project's SFT (ES): its own experiment holds only that side, paired with
    # the project's SFT on each suite it was evaluated on
    es = tmp_path / "es"
    _evaluations(es, {("post_trained", "libero_object_swap"): [False, True, True, True]})
    suites_pro([str(tmp_path / "out"), f"tiny={tmp_path / 'a'}", f"tiny:ES={es}"])
    rows = json.loads((tmp_path / "out" / "suites_pro.json").read_text())
    assert [(r["release"], r["suite"]) for r in rows[3:]] == [("ES", "libero_object_swap")]
    assert rows[3]["paired"] == {"sft": 0.5, "post_trained": 0.75, "episodes": 4, "only_a": 1, "only_b": 2,
                                 "p_value": 1.0}


def _kept(root, name, suite, policy, success, termination="oracle"):
    folder = root / f"evaluate-{name}"
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({"suite": suite, "policy": policy, "termination": termination,
                                                     "max_steps": 220, "success_rate": sum(success) / len(success)}))
    (folder / "episodes.json").write_text(json.dumps([{"task_id": 0, "init_state": i, "success": ok}
                                                      for i, ok in success.items()]))


def test_the_kept_table_pools_each_released_side_and_names_the_release(tmp_path):
    """`--kept`: no experiment, only results/<suite>/evaluate-*; a side's kept evaluations pool (init states
    0-1 + 2-3), ACT's released folders get rows of their own, what is no released checkpoint, no perturbed
    suite or no oracle termination stays out, and a missing post-trained side reads "not run" where that
    checkpoint was evaluated elsewhere, "not released" where it never was."""
    root = tmp_path / "libero_spatial"
    ck = "checkpoints/libero_spatial"
    _kept(root, "a", "libero_spatial_lan", f"{ck}/sft", {0: False, 1: False})
    _kept(root, "b", "libero_spatial_lan", f"{ck}/sft", {2: True, 3: False})
    _kept(root, "c", "libero_spatial_lan", f"{ck}/post_trained", {0: True, 1: True, 2: True, 3: False})
    _kept(root, "d", "libero_spatial_lan", f"{ck}/act_sft", {0: False, 1: False, 2: False, 3: False})
    _kept(root, "e", "libero_spatial_lan", f"{ck}/act_post_trained", {0: True, 1: False, 2: False, 3: False})
    _kept(root, "f", "libero_spatial_lan", "outputs/x/post_train_loop/0123456789abcdef/policy", {0: True})  # not released
    _kept(root, "g", "libero_spatial", f"{ck}/sft", {0: True})  # its own suite: the suites table's
    _kept(root, "h", "libero_spatial_swap", f"{ck}/sft", {0: True}, termination="fixed")
    suites_pro(["--kept", str(tmp_path / "out"), f"libero_spatial={root}"])
    rows = json.loads((tmp_path / "out" / "suites_pro.json").read_text())
    assert [(r["release"], r["suite"]) for r in rows] == [("the project's", "libero_spatial_lan"),
                                                          ("ACT", "libero_spatial_lan")]
    assert rows[0]["paired"] == {"sft": 0.25, "post_trained": 0.75, "episodes": 4, "only_a": 0, "only_b": 2,
                                 "p_value": 0.5}
    assert rows[1]["sft"] == 0.0 and rows[1]["post_trained"] == 0.25
    text = (tmp_path / "out" / "suites_pro.md").read_text()
    assert "| libero_spatial | ACT | libero_spatial_lan | lan | 220 | 0.0 % (4) | 25.0 % (4) | +25.0 | 0 / 1 | 1 |" in text
    assert "--kept" in text  # says how it was made
    _kept(root, "j", "libero_spatial_swap", f"{ck}/act_sft", {0: False})  # its other side not kept yet
    suites_pro(["--kept", str(tmp_path / "out"), f"libero_spatial={root}"])
    assert "| libero_spatial | ACT | libero_spatial_swap | swap | 220 | 0.0 % (1) | not run |" in (
        tmp_path / "out" / "suites_pro.md").read_text()
    _kept(root, "m", "libero_spatial_lan", f"{ck}/es_post_trained", {0: True, 1: True, 2: False, 3: True})
    suites_pro(["--kept", str(tmp_path / "out"), f"libero_spatial={root}"])
    rows = json.loads((tmp_path / "out" / "suites_pro.json").read_text())
    assert rows[-1]["release"] == "ES" and rows[-1]["paired"]["sft"] == 0.25  # the project's SFT, pooled
    assert rows[-1]["paired"]["only_a"] == 1 and rows[-1]["paired"]["only_b"] == 3
    goal = tmp_path / "libero_goal"  # a suite whose post-training was never released: only its SFT is kept
    _kept(goal, "k", "libero_goal", "checkpoints/libero_goal/sft", {0: True})
    _kept(goal, "l", "libero_goal_lan", "checkpoints/libero_goal/sft", {0: True, 1: False})
    suites_pro(["--kept", str(tmp_path / "out"), f"libero_spatial={root}", f"libero_goal={goal}"])
    assert "| libero_goal | the project's | libero_goal_lan | lan | 220 | 50.0 % (2) | not released |" in (
        tmp_path / "out" / "suites_pro.md").read_text()
    _kept(root, "i", "libero_spatial_lan", f"{ck}/sft", {3: True})  # an episode twice: which would count?
    with pytest.raises(Exception, match="init state 3"):
        suites_pro(["--kept", str(tmp_path / "out"), f"libero_spatial={root}"])
