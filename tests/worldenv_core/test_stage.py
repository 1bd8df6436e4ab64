"""Shared stage helpers."""
import pytest
from omegaconf import OmegaConf

from worldenv_core.stage import ConfigError, group_size, one_of, work_dir


def test_a_choice_outside_its_set_is_named_with_the_choices():
    cfg = OmegaConf.create({"policy_collections": "every", "rl": {"contexts": "episodes"}})
    assert one_of(cfg, "rl.contexts", ("episodes", "placements")) == "episodes"
    with pytest.raises(ConfigError, match=r"policy_collections must be one of \['latest', 'all'\], got 'every'"):
        one_of(cfg, "policy_collections", ("latest", "all"))


def test_a_group_of_rollouts_needs_two_for_its_leave_one_out_baseline():
    cfg = OmegaConf.create({"rl": {"n_rollouts": 2}, "one": 1, "flag": True, "half": 2.5})
    assert group_size(cfg, "rl.n_rollouts") == 2
    for key, shown in (("one", "1"), ("flag", "True"), ("half", "2.5"), ("absent", "None")):
        with pytest.raises(ConfigError, match=f"^{key} must be at least 2 .*RLOO.*got {shown}$"):
            group_size(cfg, key)


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


def test_a_scale_sets_the_default_networks_sizes_and_the_others_keep_theirs():
    """scale=tiny trains the tests' tiny networks (the smoke proves plumbing); small keeps each model config's
    own sizes; an override on the command line still wins, and the latent reflector follows the world model's."""
    from hydra.utils import instantiate

    from worldenv_core.stage import compose_config

    def sizes(scale):
        task = "+task=tiny" if scale == "tiny" else "+task=libero_spatial"
        p = compose_config("train_policy", [task, f"scale={scale}"]).policy
        w = compose_config("train_worldsim", [task, f"scale={scale}"]).worldsim
        r = compose_config("train_reflector", [task, f"scale={scale}"]).reflector
        latent = compose_config("train_reflector", [task, f"scale={scale}", "reflector=worldsim_latent"]).reflector
        return (p.hidden, list(p.backbone.widths), w.width, list(w.ae_widths), r.d_model, list(r.frame_encoder.widths),
                list(latent.frame_encoder.ae_widths))

    assert sizes("tiny") == (32, [8, 8, 8, 8], 16, [8, 16], 16, [8, 16], [8, 16])
    assert sizes("small") == (512, [16, 32, 64, 128], 48, [32, 64], 128, [32, 64, 128, 128], [32, 64])
    assert compose_config("train_policy", ["+task=tiny", "scale=tiny", "policy.hidden=64"]).policy.hidden == 64
    cfg = compose_config("train_policy", ["+task=tiny", "scale=tiny"])
    assert sum(p.numel() for p in instantiate(cfg.policy).parameters()) < 2e5  # the smoke's policy is tiny
