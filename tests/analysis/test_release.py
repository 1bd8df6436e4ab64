"""Releasing a checkpoint folder: float16 storage that loads back as float32, LeRobot's layout beside it,
a weight float16 cannot hold refused. A tiny ACT built from a config in the test (nothing downloaded)."""
import subprocess
import sys

import pytest
import torch

from analysis.release import halve, release
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import WEIGHTS, load_checkpoint, load_weights, read_config, save_model
from worldenv_core.models.lerobot_act import ACTLaplacePolicy

TINY = dict(cameras=["agentview"], chunk=4, image_size=32, dim_model=16, n_heads=2, dim_feedforward=32,
            n_encoder_layers=1, dropout=0.0)
META = {"kind": "policy", "cameras": ["agentview"], "image_size": 32, "chunk": 4, "action_dim": 7, "proprio_dim": 7}


def inputs():
    g = torch.Generator().manual_seed(0)
    return ({"agentview": torch.randint(0, 256, (3, 3, 32, 32), dtype=torch.uint8, generator=g)},
            torch.randn(3, 7, generator=g), torch.randn(3, 384, generator=g))


@pytest.fixture
def trained(tmp_path):
    torch.manual_seed(0)
    m = ACTLaplacePolicy(**TINY).eval()
    m.action_norm.set_stats(torch.ones(7), torch.full((7,), 0.5))
    save_model(tmp_path / "policy", m, {"_target_": "worldenv_core.models.lerobot_act.ACTLaplacePolicy", **TINY}, META)
    return m, tmp_path / "policy"


def test_a_half_release_halves_the_weights_and_loads_back_as_float32_with_the_same_chunk(trained, tmp_path):
    m, src = trained
    out = release(src, tmp_path / "released", half=True)
    stored = load_weights(tmp_path / "released" / WEIGHTS)
    floats = [v for v in stored.values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    assert (tmp_path / "released" / WEIGHTS).stat().st_size < 0.6 * (src / WEIGHTS).stat().st_size
    assert 0 < out["largest_relative_rounding"] < 1e-3 and out["stored_dtype"] == "float16"
    back, meta = load_checkpoint(tmp_path / "released", "policy")
    assert meta["released_from"] == "policy" and meta["stored_dtype"] == "float16"
    assert all(p.dtype == torch.float32 for p in back.parameters())
    mu_back, mu = back(*inputs())[0], m(*inputs())[0]
    assert not torch.equal(mu_back, mu) and torch.allclose(mu_back, mu, atol=5e-2)  # rounded, not changed


def test_a_release_as_trained_is_the_same_weights_and_lerobot_reads_its_layout(trained, tmp_path):
    from lerobot.policies.act.modeling_act import ACTPolicy

    m, src = trained
    release(src, tmp_path / "released", lerobot=True)
    a, b = load_weights(src / WEIGHTS), load_weights(tmp_path / "released" / WEIGHTS)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert read_config(tmp_path / "released")["model"] == read_config(src)["model"]
    lerobot = ACTPolicy.from_pretrained(tmp_path / "released" / "lerobot").eval()
    assert torch.allclose(lerobot.model(m.inputs(*inputs()))[0], m(*inputs())[0], atol=1e-6)


def test_halve_refuses_a_value_float16_cannot_hold():
    with pytest.raises(ConfigError, match="beyond float16"):
        halve({"w": torch.tensor([1.0, 1e6])})
    state, worst = halve({"w": torch.tensor([1.0, 3.0]), "n": torch.tensor(5)})
    assert state["w"].dtype == torch.float16 and state["n"].dtype == torch.int64 and worst == 0.0


def test_the_command_names_a_folder_that_is_not_a_checkpoint_in_one_line(tmp_path):
    run = subprocess.run([sys.executable, "-m", "analysis.release", str(tmp_path), str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 2 and run.stderr.startswith("error:") and "not a checkpoint folder" in run.stderr
    assert not (tmp_path / "out").exists()
