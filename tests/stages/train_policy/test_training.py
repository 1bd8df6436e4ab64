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


def test_the_scale_heads_phase_leaves_the_trunk_as_it_was_with_dropout_and_batch_norm():
    """ACT has dropout and (untrained backbone) batch norm: fitted in train mode, beta would follow dropout's
    residuals and the trunk's norm statistics would keep moving. Phase 2 changes only the scale head."""
    from stages.train_policy.training import scale_step
    from tests.worldenv_core.models.test_lerobot_act import TINY
    from worldenv_core.models.lerobot_act import ACTLaplacePolicy

    torch.manual_seed(0)
    model = ACTLaplacePolicy(**{**TINY, "dropout": 0.5}).train()  # as the Trainer hands it to a step
    trunk = {k: v.clone() for k, v in model.state_dict().items() if not k.startswith("scale_head")}
    head = [p.clone() for p in model.scale_head.parameters()]
    optimizer = torch.optim.Adam(model.scale_head.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(1)
    b = {"images": {"agentview": torch.randint(0, 256, (4, 3, 32, 32), dtype=torch.uint8, generator=g)},
         "proprio": torch.randn(4, 7, generator=g), "instruction": ["a", "b", "c", "d"],
         "actions": torch.randn(4, 4, 7, generator=g), "action_is_pad": torch.zeros(4, 4, dtype=torch.bool)}
    encoder = lambda texts: torch.randn(len(texts), 384, generator=torch.Generator().manual_seed(2))  # noqa: E731
    step = scale_step(model, optimizer, encoder, "cpu")
    first = step(b)
    for _ in range(2):
        model.train()
        step(b)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in trunk.items())  # norm statistics included
    assert any(not torch.equal(p, q) for p, q in zip(head, model.scale_head.parameters()))
    model.train()
    assert step(b)["nll"] < first["nll"]  # deterministic features: the same batch's NLL falls as the head learns
