import numpy as np
import pytest
import torch

from analysis.input_reliance import derangement, input_reliance, main, swapped
from analysis.policy_frames import PolicyFrames


class ProprioOnly(torch.nn.Module):
    """A policy whose chunk is a function of the proprio alone: the image and the instruction change nothing."""
    cameras = ["agentview"]

    def forward(self, images, proprio, instruction):
        mu = proprio[:, None, :].expand(-1, 4, -1) * 2.0
        return mu, torch.zeros_like(mu)


def frames(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return PolicyFrames({"agentview": torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=g)},
                        torch.randn(n, 7, generator=g), torch.randn(n, 384, generator=g), torch.zeros(n, dtype=torch.long))


def test_a_derangement_moves_every_frame_and_a_swap_replaces_one_input_only():
    for n in (2, 3, 7, 50):
        perm = derangement(n, seed=n)
        assert sorted(perm.tolist()) == list(range(n)) and (perm != torch.arange(n)).all()
    with pytest.raises(ValueError, match="at least two frames"):
        derangement(1)
    f, perm = frames(), derangement(6)
    s = swapped(f, "proprio", perm)
    assert torch.equal(s.proprio, f.proprio[perm]) and s.images is f.images and s.instruction is f.instruction


def test_an_input_the_policy_ignores_changes_nothing_and_one_it_reads_does():
    r = input_reliance(ProprioOnly(), frames())
    assert r["image_change"] == 0.0 and r["instruction_change"] == 0.0
    assert r["proprio_change"] > 0 and r["proprio_share"] > 0.5 and "backbone_mean_abs" not in r


def test_the_project_policy_and_an_act_report_every_input_and_acts_backbone(tmp_path):
    from hydra.utils import instantiate

    from tests.conftest import synthetic_episode
    from tests.worldenv_core.models.test_lerobot_act import TINY
    from tests.worldenv_core.models.test_policy import small_config
    from worldenv_core.data.mcap_io import write_episode
    from worldenv_core.models.checkpoint import save_model

    torch.manual_seed(0)
    small = instantiate(small_config()).eval()
    r = input_reliance(small, frames(8))
    assert all(r[f"{w}_change"] > 0 for w in ("image", "proprio", "instruction"))
    from worldenv_core.models.lerobot_act import ACTLaplacePolicy

    act = ACTLaplacePolicy(**TINY).eval()
    r = input_reliance(act, frames(8))
    assert r["backbone_mean_abs"] > 0 and 0 <= r["backbone_zero_share"] < 1 and r["image_change"] > 0
    # the command line: a policy folder and recorded episodes -> the table and the JSON
    rng = np.random.default_rng(0)
    for k in range(2):
        write_episode(tmp_path / f"ep{k}.mcap", synthetic_episode(rng, size=32, length=17))
    meta = {"kind": "policy", "cameras": ["agentview"], "image_size": 32, "chunk": 4, "action_dim": 7, "proprio_dim": 7}
    save_model(tmp_path / "act", act, {"_target_": "worldenv_core.models.lerobot_act.ACTLaplacePolicy", **TINY}, meta)
    main(["--policy", str(tmp_path / "act"), "--frames", str(tmp_path / "ep*.mcap"), "--every", "4",
          "--json", str(tmp_path / "out.json")])
    import json
    out = json.loads((tmp_path / "out.json").read_text())[str(tmp_path / "act")]
    assert out["frames"] == 10 and out["image_change"] > 0
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path / "act"), "--frames", str(tmp_path / "none*.mcap")])
