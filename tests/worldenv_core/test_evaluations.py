"""Kept evaluations read, pooled and paired (`worldenv_core.evaluations`): the comparisons of two
policies on the real benchmark all start here."""
import json

import pytest

from worldenv_core.errors import ConfigError
from worldenv_core.evaluations import checkpoint_name, compare, paired_gain, pooled_episodes, same_policy


def _kept(folder, policy, outcomes, termination="oracle", digest=None):
    folder.mkdir(parents=True)
    summary = {"policy": policy, "termination": termination, "suite": "libero_spatial",
               **({"policy_digest": digest} if digest else {})}
    (folder / "results.json").write_text(json.dumps(summary))
    (folder / "episodes.json").write_text(json.dumps([{"task_id": t, "init_state": i, "success": s}
                                                      for (t, i), s in outcomes.items()]))
    return str(folder)


def test_ranges_of_one_policy_pool_and_another_policy_or_an_episode_twice_is_refused(tmp_path):
    first = _kept(tmp_path / "a0", "ckpt/sft", {(0, 0): True, (0, 1): False})
    second = _kept(tmp_path / "a1", "ckpt/sft", {(0, 2): True})
    episodes, setting = pooled_episodes(None, [first, second])
    assert episodes == {(0, 0): True, (0, 1): False, (0, 2): True} and setting["policy"] == "ckpt/sft"
    with pytest.raises(ConfigError, match="twice|is in"):
        pooled_episodes(None, [first, first])
    other = _kept(tmp_path / "b", "ckpt/moved", {(0, 3): True})
    with pytest.raises(ConfigError, match="other weights"):
        pooled_episodes(None, [first, other])
    fixed = _kept(tmp_path / "f", "ckpt/sft", {(0, 4): True}, termination="fixed")
    with pytest.raises(ConfigError, match="termination"):
        pooled_episodes(None, [first, fixed])


def test_one_policy_is_one_digest_whatever_its_folder_is_called():
    assert same_policy({"policy": "a/x", "policy_digest": "d"}, {"policy": "b/y", "policy_digest": "d"})
    assert not same_policy({"policy": "a/x", "policy_digest": "d"}, {"policy": "a/x", "policy_digest": "e"})
    assert checkpoint_name("/abc/post_train_loop/0123456789abcdef/policy") == "post_train_loop/0123456789abcdef"
    assert checkpoint_name("/repo/checkpoints/libero_spatial/sft") == "libero_spatial/sft"


def test_two_policies_compare_on_the_episodes_both_ran():
    a = {(0, i): i < 5 for i in range(10)}
    b = {**{(0, i): i < 8 for i in range(10)}, (1, 0): True}  # (1, 0): only b ran it
    result = compare(a, b)
    assert result["episodes"] == 10 and (result["only_a"], result["only_b"]) == (0, 3)
    assert result["a"] == pytest.approx(0.5) and result["b"] == pytest.approx(0.8)
    assert result["p_value"] == pytest.approx(0.25) and [t["task_id"] for t in result["per_task"]] == [0]
    gain = paired_gain(a, b, sorted(a))
    assert gain["gain"] == pytest.approx(0.3) and gain["ci"][0] < 0.3 < gain["ci"][1]
    with pytest.raises(ConfigError, match="share no episode"):
        compare(a, {(5, 5): True})
