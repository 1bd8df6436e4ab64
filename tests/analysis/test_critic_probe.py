"""The critic probe on a rollout journal written as the stage writes one: one journal is fitted on
its even groups and judged on its odd ones, RLOO beside each lambda; broken groups and a missing
behaviour policy are named."""
import json
import pickle
import zlib

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from analysis.critic_probe import main, read_journal
from worldenv_core.envs.replay import RealStart
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import save_model

POLICY = {"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": ["agentview"], "chunk": 8, "hidden": 32,
          "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                       "cond_dim": 384, "widths": [8, 8], "keypoints": 4}}


def journal(tmp_path, contract, groups=4, n=2, chunks=3):
    """`groups` x `n` rollouts of 3 chunks of the tiny task's shapes, one success per group."""
    torch.manual_seed(0)
    folder = tmp_path / "0123456789abcdef"
    folder.mkdir()
    save_model(tmp_path / "0123456789abcdef_behaviour", instantiate(POLICY), POLICY,
               {"kind": "policy", **contract().meta(), "cameras": ["agentview"]})
    rng = np.random.default_rng(0)
    for i in range(groups * n):
        success = i % n == 0
        result = {"index": i, "start": RealStart(task_id=0, seed=i // n), "seed": i, "error": None,
                  "frames": [rng.integers(0, 255, (64, 64, 3), dtype=np.uint8) for _ in range(chunks)],
                  "proprio": [rng.normal(size=7).astype(np.float32) for _ in range(chunks)],
                  "actions": [rng.normal(size=(8, 7)).astype(np.float32) for _ in range(chunks)],
                  "executed": [8] * chunks, "first_success": 20 if success else None,
                  "seconds": {"physics": 1.0}}
        (folder / f"{i:05d}.rollout").write_bytes(zlib.compress(pickle.dumps(((i,), result))))
    return folder


def test_one_journal_is_fitted_on_its_even_groups_and_judged_on_its_odd_ones(tmp_path, contract):
    folder = journal(tmp_path, contract)
    out = main(["+task=tiny", "scale=tiny", "rl.n_rollouts=2", "rl.horizon=24", "--fit", str(folder), "--judge",
                str(folder), "--steps", "20", "--minibatch", "8", "--lambdas", "1", "0.5", "--json",
                str(tmp_path / "probe.json"), "--outcomes", str(tmp_path / "outcomes.json")])
    assert out["fit_rollouts"] == out["judge_rollouts"] == 4 and out["mixed_groups"] == 2
    assert [r["advantages"] for r in out["gradients"]] == ["rloo", "gae_1", "gae_0.5"]
    assert all(r["gradient_noise_sq"] > 0 for r in out["gradients"])
    assert out["judge_success"] == 0.5 and len(out["auroc_by_depth"]) == 4
    assert json.loads((tmp_path / "probe.json").read_text())["gradients"][0]["advantages"] == "rloo"
    (outcomes,) = json.loads((tmp_path / "outcomes.json").read_text()).values()  # one journal, both roles
    assert outcomes == {f"task0/placement{k}": [1, 2] for k in range(4)}


def test_an_unfinished_group_is_left_out_and_too_few_or_no_policy_is_an_error(tmp_path, contract):
    folder = journal(tmp_path, contract, groups=3)
    (folder / "00005.rollout").unlink()  # group 2 lost a rollout: an iteration cut short
    assert [r["index"] for r in read_journal(folder, 2)] == [0, 1, 2, 3]
    (folder / "00003.rollout").unlink()
    with pytest.raises(ConfigError, match="1 whole groups of 2 rollouts"):
        read_journal(folder, 2)
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(SystemExit):
        main(["+task=tiny", "scale=tiny", "--fit", str(other), "--judge", str(other)])
