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
