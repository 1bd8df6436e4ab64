import json

import numpy as np
import pytest
import torch

from analysis.random_update import main, mean_update, mirror_update, random_update, scaled_update
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import load_model, save_state

LINEAR = {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}


def states():
    base = {"weight": torch.randn(2, 3, generator=torch.Generator().manual_seed(1)), "bias": torch.zeros(2),
            "count": torch.tensor([4])}
    like = {"weight": base["weight"] + 0.01 * torch.randn(2, 3, generator=torch.Generator().manual_seed(2)),
            "bias": base["bias"].clone(), "count": base["count"].clone()}
    return base, like


def test_each_tensor_moves_as_far_as_the_update_in_another_direction():
    base, like = states()
    out, moved = random_update(base, like, seed=0, scale=3.0)
    assert moved == 1
    step, update = out["weight"] - base["weight"], like["weight"] - base["weight"]
    assert torch.allclose(step.norm(), 3.0 * update.norm(), rtol=1e-5)
    assert torch.nn.functional.cosine_similarity(step.flatten(), update.flatten(), dim=0) < 0.99
    assert torch.equal(out["bias"], base["bias"]) and torch.equal(out["count"], base["count"])  # unchanged stays so


def test_the_seed_decides_the_direction():
    base, like = states()
    assert torch.equal(random_update(base, like, 0)[0]["weight"], random_update(base, like, 0)[0]["weight"])
    assert not torch.equal(random_update(base, like, 0)[0]["weight"], random_update(base, like, 1)[0]["weight"])


def test_policies_that_do_not_match_are_refused():
    base, like = states()
    with pytest.raises(ConfigError, match="different tensors"):
        random_update(base, {"weight": like["weight"]}, 0)
    with pytest.raises(ConfigError, match="shape"):
        random_update(base, {**like, "bias": torch.zeros(3)}, 0)
    with pytest.raises(ConfigError, match="scale"):
        random_update(base, like, 0, scale=0.0)


def sft_and_post(tmp_path):
    """A policy checkpoint and one 'post-trained' from it (every tensor + 0.01) under tmp_path/sft, /post."""
    torch.manual_seed(0)
    sft = torch.nn.Linear(3, 2)
    post = {k: v + 0.01 for k, v in sft.state_dict().items()}
    save_state(tmp_path / "sft", sft.state_dict(), LINEAR, {"kind": "policy"})
    save_state(tmp_path / "post", post, LINEAR, {"kind": "policy"})
    return sft, post


def test_cli_writes_a_checkpoint_that_loads_and_says_what_it_is(tmp_path, capsys):
    sft, post = sft_and_post(tmp_path)
    main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "post"), "--out", str(tmp_path / "rand"),
          "--seed", "3"])
    model, cfg = load_model(tmp_path / "rand")
    assert isinstance(model, torch.nn.Linear)
    assert cfg["meta"]["random_update"]["seed"] == 3 and cfg["meta"]["random_update"]["tensors_moved"] == 2
    for k, v in model.state_dict().items():
        assert torch.allclose((v - sft.state_dict()[k]).norm(), (post[k] - sft.state_dict()[k]).norm(), rtol=1e-5)
    assert not (tmp_path / "rand.tmp").exists()


def test_cli_refuses_a_non_policy(tmp_path, capsys):
    save_state(tmp_path / "sft", torch.nn.Linear(3, 2).state_dict(), LINEAR, {"kind": "reflector"})
    save_state(tmp_path / "post", torch.nn.Linear(3, 2).state_dict(), LINEAR, {"kind": "policy"})
    with pytest.raises(SystemExit) as exit_:
        main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "post"), "--out", str(tmp_path / "rand")])
    assert exit_.value.code == 2 and "not a policy" in capsys.readouterr().err
    assert not (tmp_path / "rand").exists()
    json.loads((tmp_path / "sft" / "config.json").read_text())  # inputs untouched


def test_action_change_is_zero_for_the_same_weights_and_grows_with_the_move(tmp_path):
    from hydra.utils import instantiate

    from tests.conftest import synthetic_episode
    from tests.worldenv_core.models.test_policy import small_config
    from analysis.random_update import action_changes
    from worldenv_core.data.mcap_io import write_episode

    write_episode(tmp_path / "ep.mcap", synthetic_episode(np.random.default_rng(0), size=32, length=16))
    torch.manual_seed(0)
    base = instantiate(small_config()).eval()
    like = {k: v + 1e-3 * torch.randn_like(v) if v.is_floating_point() else v for k, v in base.state_dict().items()}
    moved = []
    for scale in (1.0, 10.0):
        moved.append(instantiate(small_config()).eval())
        moved[-1].load_state_dict(random_update(base.state_dict(), like, seed=0, scale=scale)[0])
    changes = action_changes(base, moved, [tmp_path / "ep.mcap"], every=4)
    assert action_changes(base, [base], [tmp_path / "ep.mcap"]) == [0.0]
    assert 0.0 < changes[0] < changes[1]


def test_the_mirror_moves_by_minus_the_update_and_leaves_the_rest():
    base, like = states()
    out, moved = mirror_update(base, like)
    assert moved == 1
    assert torch.allclose(out["weight"] - base["weight"], -(like["weight"] - base["weight"]), atol=1e-6)
    assert torch.equal(out["bias"], base["bias"]) and torch.equal(out["count"], base["count"])
    half, _ = mirror_update(base, like, scale=0.5)
    assert torch.allclose(half["weight"] - base["weight"], -0.5 * (like["weight"] - base["weight"]), atol=1e-6)
    with pytest.raises(ConfigError, match="different tensors"):
        mirror_update(base, {"weight": like["weight"]})


def test_cli_mirror_records_its_direction(tmp_path, capsys):
    sft, post = sft_and_post(tmp_path)
    main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "post"), "--out", str(tmp_path / "mirror"),
          "--mirror"])
    model, cfg = load_model(tmp_path / "mirror")
    assert cfg["meta"]["random_update"]["direction"] == "mirror" and cfg["meta"]["random_update"]["seed"] is None
    for k, v in model.state_dict().items():
        assert torch.allclose(v, sft.state_dict()[k] - 0.01, atol=1e-6)
    assert "reverse of its update" in capsys.readouterr().out


def test_the_mean_of_several_updates_keeps_what_they_share():
    base, like = states()
    shared = like["weight"] - base["weight"]
    noise = 0.01 * torch.randn(2, 3, generator=torch.Generator().manual_seed(3))
    seeds = [{**like, "weight": base["weight"] + shared + noise}, {**like, "weight": base["weight"] + shared - noise}]
    mean = mean_update(base, seeds)
    assert torch.allclose(mean["weight"], like["weight"], atol=1e-6)  # the opposite draws cancel, the shared part stays
    assert torch.equal(mean["bias"], base["bias"]) and torch.equal(mean["count"], base["count"])
    assert mean_update(base, [like]) is like
    along, moved = scaled_update(base, mean, 2.0)
    assert moved == 1 and torch.allclose(along["weight"] - base["weight"], 2.0 * shared, atol=1e-6)
    with pytest.raises(ConfigError, match="at least one"):
        mean_update(base, [])
    with pytest.raises(ConfigError, match="different tensors"):
        mean_update(base, [like, {"weight": like["weight"]}])


def test_cli_along_the_mean_update_of_two_seeds(tmp_path, capsys):
    sft, post = sft_and_post(tmp_path)
    other = {k: v + 0.03 for k, v in sft.state_dict().items()}
    save_state(tmp_path / "post2", other, LINEAR, {"kind": "policy"})
    main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "post"), str(tmp_path / "post2"),
          "--out", str(tmp_path / "mean"), "--along"])
    model, cfg = load_model(tmp_path / "mean")
    record = cfg["meta"]["random_update"]
    assert record["direction"] == "update" and record["seed"] is None and len(record["like"]) == 2
    for k, v in model.state_dict().items():
        assert torch.allclose(v, sft.state_dict()[k] + 0.02, atol=1e-6)
    assert "the mean of their 2 updates" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # one direction at a time
        main(["--policy", str(tmp_path / "sft"), "--like", str(tmp_path / "post"), "--out", str(tmp_path / "x"),
              "--along", "--mirror"])
