"""Shared stage helpers."""
import pytest
from omegaconf import OmegaConf

from worldenv_core.stage import ConfigError, one_of, work_dir


def test_a_choice_outside_its_set_is_named_with_the_choices():
    cfg = OmegaConf.create({"policy_collections": "every", "rl": {"contexts": "episodes"}})
    assert one_of(cfg, "rl.contexts", ("episodes", "placements")) == "episodes"
    with pytest.raises(ConfigError, match=r"policy_collections must be one of \['latest', 'all'\], got 'every'"):
        one_of(cfg, "policy_collections", ("latest", "all"))


def test_work_dir_depends_on_settings_and_inputs_not_their_order():
    cfg = {"lr": 1e-3}
    a = work_dir("exp", "train_reflector", cfg, ["collect-1", "collect-2"])
    assert a == work_dir("exp", "train_reflector", cfg, ["collect-2", "collect-1"])
    assert a.parent.as_posix() == "exp/train_reflector"
    # a newer collection (same settings) is a new run, never a resume of the one trained on the old data
    assert a != work_dir("exp", "train_reflector", cfg, ["collect-1", "collect-3"])
    assert a != work_dir("exp", "train_reflector", {"lr": 1e-4}, ["collect-1", "collect-2"])


def test_scale_settings_that_only_choose_evaluation_do_not_name_work():
    scale = {"name": "small", "reflector_steps": 1500}
    a = work_dir("exp", "train_reflector", {"scale": scale}, [])
    assert a == work_dir("exp", "train_reflector", {"scale": {**scale, "eta_folds": 5}}, [])
    assert a != work_dir("exp", "train_reflector", {"scale": {**scale, "reflector_steps": 3000}}, [])
