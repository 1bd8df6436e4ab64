"""The verdict by context depth: pairs grouped by how far into their demo they start, each group judged."""
import json
from fractions import Fraction

import pytest

from analysis.verdict_depth import by_depth, depths, plot_depth
from tests.worldenv_core.imagination.test_verdict import _row
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.verdict import verdict_metrics


def _at(start, kind, scores, first, context):
    return {**_row(scores, first=first, context=context), "start": start, "context_kind": kind}


def test_depth_is_the_frames_rank_within_its_demo_and_zero_at_a_start():
    rows = [_at("init0", "init", [0], None, 0), _at("d/a.mcap@0", "episode", [0], None, 1),
            _at("d/a.mcap@30", "episode", [0], None, 2), _at("d/a.mcap@60", "episode", [0], None, 3),
            _at("d/b.mcap@40", "episode", [0], None, 4), _at("d/b.mcap@20", "episode", [0], None, 5),
            _at("d/b.mcap@20", "episode", [0], None, 5)]
    assert depths(rows) == [0, 0, Fraction(1, 3), Fraction(2, 3), Fraction(2, 3), Fraction(1, 3), Fraction(1, 3)]
    # a demo that lost a frame (its prefix did not replay) keeps its frames' places: 40 and 80 of 20..100
    five = [_at(f"d/a.mcap@{f}", "episode", [0], None, i) for i, f in enumerate((20, 40, 60, 80, 100))]
    four = [_at(f"d/b.mcap@{f}", "episode", [0], None, 5 + i) for i, f in enumerate((17, 33, 67, 83))]  # 50 lost
    assert depths(five + four)[5:] == [Fraction(1, 6), Fraction(2, 6), Fraction(4, 6), Fraction(5, 6)]


def test_each_depth_is_judged_as_one_set(tmp_path):
    # from starts imagination calls successes that never happen; from 2/3 of the way it agrees with reality
    start = [_at(f"init{c}", "init", [0, 0.9], None, c) for c in range(4)]
    late = [_at(f"d/e{c}.mcap@{f}", "episode", [0, s], first, 10 + 2 * c + (f > 30))
            for c in range(3) for f, s, first in ((30, 0.1, None), (60, 0.9, 8))]
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "fidelity.json").write_text(json.dumps({"headline_policy": "p", "eta": 0.5, "judges": {}}))
    (folder / "pairs.json").write_text(json.dumps({"p": {"rows": start + late}}))
    out = by_depth([folder])
    assert list(out) == ["0", "1/3", "2/3"]
    assert out["0"]["rollouts"] == 4 and out["0"]["hack_rate"] == 1.0 and out["0"]["real_success"] == 0.0
    assert out["2/3"]["hack_rate"] == 0.0 and out["2/3"]["f1"] == 1.0
    assert out["1/3"]["imagined_success"] == 0.0 == verdict_metrics(late[::2], 0.5)["imagined_success"]
    assert plot_depth(out, tmp_path / "depth.png").stat().st_size > 0
    with pytest.raises(ConfigError, match="did not judge"):
        by_depth([folder], reflector="k")
    # another run of the same demos with one frame each (at 1/2): depths are read per run, so they pool
    other = tmp_path / "other"
    other.mkdir()
    (other / "fidelity.json").write_text((folder / "fidelity.json").read_text())
    (other / "pairs.json").write_text(json.dumps({"p": {"rows": [_at("d/e0.mcap@45", "episode", [0, 0.1], None, 0)]}}))
    both = by_depth([folder, other])
    assert list(both) == ["0", "1/3", "1/2", "2/3"] and both["1/2"]["rollouts"] == 1 and both["2/3"]["rollouts"] == 3
