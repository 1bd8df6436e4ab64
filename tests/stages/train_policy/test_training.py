"""train_policy's imagined-proprio augmentation: the kinematic model's drifting state in place of the real one."""
import numpy as np
import torch

from stages.train_policy.training import ImaginedProprio


def episodes(n=2, length=40, seed=0):
    rng = np.random.default_rng(seed)

    class Ep:
        def __init__(self):
            self.actions = rng.uniform(-1, 1, (length, 7))
            steps = np.cumsum(rng.normal(0, 0.004, (length + 1, 7)), axis=0)
            self.proprio = np.concatenate([steps[:, :3] + [0, 0, 1.0], steps[:, 3:6] + [3.0, 0, 0],
                                           np.clip(0.5 + steps[:, 6:], 0, 1)], axis=1)
    return [Ep() for _ in range(n)]


def batch(eps, pairs):
    return {"episode_index": torch.tensor([e for e, _ in pairs]), "frame_index": torch.tensor([t for _, t in pairs]),
            "proprio": torch.stack([torch.as_tensor(eps[e].proprio[t], dtype=torch.float32) for e, t in pairs])}


def test_one_step_back_is_the_kinematic_step_from_the_frame_before():
    eps = episodes()
    aug = ImaginedProprio(eps, fraction=1.0, max_steps=1, seed=0)
    b = batch(eps, [(0, 0), (0, 5), (1, 30)])
    out = aug(b)
    assert torch.equal(out[0], b["proprio"][0])  # the first frame has no past: kept
    for row, (e, t) in ((1, (0, 5)), (2, (1, 30))):
        zero = (torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
        expect, _ = aug.kinematics.step(torch.as_tensor(eps[e].proprio[t - 1])[None], torch.as_tensor(eps[e].actions[t - 1])[None], zero)
        np.testing.assert_allclose(out[row].numpy(), expect[0].float().numpy(), rtol=1e-5, atol=1e-6)


def test_longer_integrations_drift_and_the_draw_repeats_for_the_same_batch():
    eps = episodes(length=120)
    aug = ImaginedProprio(eps, fraction=1.0, max_steps=100, seed=0)
    b = batch(eps, [(0, 110), (1, 100), (0, 60), (1, 3)])
    out = aug(b)
    assert torch.equal(out, aug(b))  # drawn from the batch: a resumed run sees the same
    assert (out[:, :3] - b["proprio"][:, :3]).norm(dim=1).max() > 0.01  # drifted by centimetres somewhere
    assert torch.equal(ImaginedProprio(eps, fraction=0.0, max_steps=100, seed=0)(b), b["proprio"])
    mixed = ImaginedProprio(eps, fraction=0.5, max_steps=100, seed=1)(batch(eps, [(0, t) for t in range(1, 101)]))
    kept = (mixed == batch(eps, [(0, t) for t in range(1, 101)])["proprio"]).all(dim=1).float().mean()
    assert 0.3 < kept < 0.7
