"""ES members' size: the action change by sigma on frames, and members laid out per sigma on a ledger's starts."""
import numpy as np
import pytest
import torch

from analysis.member_size import action_change, by_member, main, members


def test_members_are_the_policy_then_antithetic_pairs_per_sigma_with_shared_seeds():
    ms = members([0.01, 0.05], pairs=2, seed=3)
    assert len(ms) == 1 + 2 * 2 * 2 and ms[0][1] == 0.0
    seeds = [s for s, _ in ms[1:5:2]]
    assert [c for _, c in ms[1:5]] == [0.01, -0.01, 0.01, -0.01] and [s for s, _ in ms[5::2]] == seeds
    assert members([0.01], 1, seed=3)[1] == ms[1]  # the same seed, the same directions


def test_outcomes_are_counted_per_start_for_each_sigma():
    success = torch.tensor([[1, 0, 1, 1, 1, 0, 0, 0, 1],
                            [0, 0, 0, 0, 1, 1, 1, 1, 1]], dtype=torch.bool)  # 2 starts x (policy + 2 x 4 members)
    assert by_member(success, [0.01, 0.05], pairs=2) == {"policy": [1, 0], "sigma 0.01": [3, 1], "sigma 0.05": [1, 4]}


def test_the_action_change_grows_with_sigma(tmp_path):
    from hydra.utils import instantiate

    from analysis.policy_frames import policy_frames
    from tests.conftest import synthetic_episode
    from tests.worldenv_core.models.test_policy import small_config
    from worldenv_core.data.mcap_io import write_episode
    from worldenv_core.models.text import InstructionEncoder

    rng = np.random.default_rng(0)
    write_episode(tmp_path / "ep.mcap", synthetic_episode(rng, size=32, length=16))
    torch.manual_seed(0)
    policy = instantiate(small_config()).eval()
    frames = policy_frames([tmp_path / "ep.mcap"], policy.cameras, InstructionEncoder(), every=4)
    change = action_change(policy, frames, [0.01, 0.1], directions=2)
    assert 0 < change[0.01] < change[0.1]


def test_bad_input_is_named_before_any_model_loads(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["+task=tiny", "--policy", str(tmp_path), "--frames", "x", "--sigma", "0"])
    assert "--sigma must be positive" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["+task=tiny", "--policy", str(tmp_path), "--ledger", str(tmp_path), "--iterations", "3", "--sigma", "0.01"])
    assert "iter_0003.json" in capsys.readouterr().err
