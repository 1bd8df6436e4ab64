"""Ranking policies in imagination against their kept real evaluations."""
import json

import pytest

from analysis.policy_ranking import main, ranking
from tests.worldenv_core.imagination.test_verdict import _row
from worldenv_core.errors import ConfigError


def _evaluation(folder, policy, successes, first_init_state=0):
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps({"policy": policy, "termination": "oracle", "suite": "s"}))
    (folder / "episodes.json").write_text(json.dumps(
        [{"task_id": 0, "init_state": first_init_state + i, "success": s} for i, s in enumerate(successes)]))
    return str(folder)


def _paired_run(folder, imagined_hits: dict[str, int]):
    """Per policy 4 contexts x 1 rollout: the first `hits` imagined successes (0.9 > eta), the real
    outcome of the same actions a success on contexts 0-1 only; a judge that calls none."""
    folder.mkdir()
    pairs = {}
    for policy, hits in imagined_hits.items():
        rows = [dict(_row([0.0, 0.9 if c < hits else 0.1], first=4 if c < 2 else None, context=c),
                     more_reflectors={"j": {"imagined_scores": [0.0, 0.0], "real_scores": [0.0, 0.0]}})
                for c in range(4)]
        pairs[f"{policy}@1"] = {"rows": rows}
    pairs["checkpoints/g/a@3"] = {"rows": pairs["checkpoints/g/a@1"]["rows"]}  # another noise: not this policy's skill
    (folder / "fidelity.json").write_text(json.dumps({"eta": 0.5, "judges": {"j": {"eta": 0.5}}}))
    (folder / "pairs.json").write_text(json.dumps(pairs))
    return folder


def test_imagined_success_is_ranked_against_the_kept_evaluations_of_each_checkpoint(tmp_path):
    run = _paired_run(tmp_path / "run", {"checkpoints/g/a": 3, "checkpoints/g/b": 1, "checkpoints/g/c": 2})
    real = [_evaluation(tmp_path / "a0", "/elsewhere/checkpoints/g/a", [1, 1, 0]),
            _evaluation(tmp_path / "a1", "checkpoints/g/a", [1], first_init_state=3),  # one policy, two evaluations
            _evaluation(tmp_path / "b", "checkpoints/g/b", [0, 0, 0, 1]),
            _evaluation(tmp_path / "c", "checkpoints/g/c", [1, 0, 0, 1])]
    out = ranking(run, real, draws=50)
    head = out["headline"]
    assert head["episodes"] == 4 and head["contexts"] == 4
    assert head["policies"]["g/a"] == {"imagined_success": 0.75, "pairs_real_success": 0.5, "evaluation_success": 0.75}
    assert head["imagined_vs_evaluation"]["spearman"] == pytest.approx(1.0)
    lo, hi = head["imagined_vs_evaluation"]["ci95"]
    assert -1.0 <= lo <= hi <= 1.0
    # the pairs' real outcome is the same for all three: that side ranks nothing
    assert head["pairs_vs_evaluation"]["spearman"] != head["pairs_vs_evaluation"]["spearman"]  # nan
    assert all(m["imagined_success"] == 0.0 for m in out["j"]["policies"].values())
    # the command line: the table, the figures as JSON and the plot
    main([str(run), "--real", *real, "--json", str(tmp_path / "r.json"), "--plot", str(tmp_path / "r.png")])
    assert json.loads((tmp_path / "r.json").read_text())["headline"]["policies"]["g/b"]["evaluation_success"] == 0.25
    assert (tmp_path / "r.png").stat().st_size > 0
    with pytest.raises(ConfigError, match="a ranking needs 3"):
        ranking(run, real[:2], draws=5)
