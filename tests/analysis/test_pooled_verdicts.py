"""Pooling kept paired-replay runs: the pairs of both runs judged as one set, by each reflector."""
import json

import pytest

from analysis.pooled_verdicts import pooled
from tests.worldenv_core.imagination.test_verdict import _row
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.verdict import as_judged_by, verdict_metrics


def _run(folder, rows, eta=0.5, judge_eta=0.3):
    folder.mkdir()
    for r in rows:  # a further reflector scoring the same pairs higher
        r["more_reflectors"] = {"j": {"imagined_scores": [s + 0.2 for s in r["imagined_scores"]],
                                      "real_scores": r["real_scores"]}}
    (folder / "fidelity.json").write_text(json.dumps({"headline_policy": "p", "eta": eta,
                                                      "judges": {"j": {"eta": judge_eta}}}))
    (folder / "pairs.json").write_text(json.dumps({"p": {"rows": rows}}))
    return folder


def test_pooled_runs_are_judged_as_one_set_by_each_reflector(tmp_path):
    a = [_row([0, 0.9], first=8, context=0), _row([0, 0.6], first=None, context=1)]
    b = [_row([0, 0.2], first=4, context=0), _row([0, 0.05], first=None, context=1)]
    out = pooled([_run(tmp_path / "a", a), _run(tmp_path / "b", b)])
    want = verdict_metrics(a + b, 0.5)
    assert out["headline"]["rollouts"] == 4 and out["headline"]["f1"] == want["f1"] == 0.5
    assert out["headline"]["auroc"] == want["auroc"] and len(out["headline"]["auroc_ci95"]) == 2
    judged_by_j = verdict_metrics([as_judged_by(r, "j") for r in a + b], 0.3)
    assert out["j"]["eta"] == 0.3 and out["j"]["hacks"] == judged_by_j["hacks"] == 1  # 0.6 + 0.2 passes 0.3
    # both at once: j passes 0.3 wherever the headline passes 0.5, so together they judge as the headline
    both = pooled([tmp_path / "a", tmp_path / "b"], ensemble=True)["all of them"]
    assert both["eta"] == 0.0 and both["hacks"] == out["headline"]["hacks"] == 1
    assert both["imagined_success"] == out["headline"]["imagined_success"] < out["j"]["imagined_success"]
    with pytest.raises(ConfigError, match="different etas"):
        pooled([tmp_path / "a", _run(tmp_path / "c", [_row([0, 0.1], first=None)], eta=0.9)])
    # one further reflector pools across runs whose own reflectors differ
    only_j = pooled([tmp_path / "a", tmp_path / "b", tmp_path / "c"], reflector="j")
    assert list(only_j) == ["j"] and only_j["j"]["rollouts"] == 5
    with pytest.raises(ConfigError, match="did not judge every run"):
        pooled([tmp_path / "a"], reflector="k")


def test_pooled_all_policies_takes_every_paired_policy(tmp_path):
    folder = _run(tmp_path / "a", [_row([0, 0.9], first=8, context=0)])
    pairs = json.loads((folder / "pairs.json").read_text())
    pairs["q"] = {"rows": pairs["p"]["rows"] + pairs["p"]["rows"]}
    (folder / "pairs.json").write_text(json.dumps(pairs))
    assert pooled([folder])["headline"]["rollouts"] == 1
    assert pooled([folder], all_policies=True)["headline"]["rollouts"] == 3
