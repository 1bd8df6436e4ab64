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
