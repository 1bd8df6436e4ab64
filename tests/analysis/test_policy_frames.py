import numpy as np
import pytest
import torch

from analysis.policy_frames import mean_actions, policy_frames


def test_every_nth_frame_of_each_episode_with_its_task_and_the_policys_actions_in_any_batch(tmp_path):
    from hydra.utils import instantiate

    from tests.conftest import synthetic_episode
    from tests.worldenv_core.models.test_policy import small_config
    from worldenv_core.data.mcap_io import write_episode
    from worldenv_core.models.text import InstructionEncoder

    rng = np.random.default_rng(0)
    for k, length in enumerate((16, 9)):
        ep = synthetic_episode(rng, size=32, length=length)
        ep.meta.task_id = k + 3
        write_episode(tmp_path / f"ep{k}.mcap", ep)
    torch.manual_seed(0)
    policy = instantiate(small_config()).eval()
    frames = policy_frames([tmp_path / "ep0.mcap", tmp_path / "ep1.mcap"], policy.cameras, InstructionEncoder(), every=4)
    # frames 0, 4, ..., 16 of a 17-frame episode, then 0, 4, 8 of a 10-frame one
    assert len(frames) == 5 + 3 and frames.task_ids.tolist() == [3] * 5 + [4] * 3
    assert all(v.dtype == torch.uint8 and len(v) == 8 for v in frames.images.values())
    whole = mean_actions(policy, frames)
    assert whole.shape == (8, 4, 7) and torch.allclose(mean_actions(policy, frames, batch=3), whole, atol=1e-6)
    with pytest.raises(ValueError, match="at least one recorded episode"):
        policy_frames([], policy.cameras, InstructionEncoder())
