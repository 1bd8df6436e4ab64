"""A LeRobot ACT policy behind the Laplace interface: shapes, the two training phases, the RL
parameter groups, this project's checkpoint folder and LeRobot's own layout, offline weights.
Built from a tiny config in the test (nothing downloaded)."""
import pytest
import torch

from worldenv_core.models.laplace import laplace_log_prob
from worldenv_core.models.lerobot_act import ACTLaplacePolicy
from worldenv_core.rl.loop import policy_param_groups

TINY = dict(cameras=["agentview"], chunk=4, image_size=32, dim_model=16, n_heads=2, dim_feedforward=32,
            n_encoder_layers=1, dropout=0.0)


def inputs(b=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return ({"agentview": torch.randint(0, 256, (b, 3, 32, 32), dtype=torch.uint8, generator=g)},
            torch.randn(b, 7, generator=g), torch.randn(b, 384, generator=g))


def policy(seed=0):
    torch.manual_seed(seed)
    return ACTLaplacePolicy(**TINY).eval()


def test_it_predicts_a_chunk_and_its_laplace_scale_and_both_heads_read_the_decoder_tokens():
    m = policy()
    mu, beta = m(*inputs())
    assert mu.shape == beta.shape == (3, 4, 7)
    assert (beta > m.beta_min).all() and (beta < m.beta_max).all()
    f = m.features(*inputs())
    assert f.shape == (3, 4, 16) and torch.allclose(m.action_head(f), mu)
    other = m(*inputs(seed=1))[0]
    assert not torch.allclose(other, mu)  # it reads its inputs
    lang = inputs()[2]
    assert not torch.allclose(m(inputs()[0], inputs()[1], -lang)[0], mu)  # the instruction included


def test_rl_gradients_reach_act_and_the_groups_split_the_heads_from_the_rest():
    m = policy().train()
    images, proprio, lang = inputs()
    mu, beta = m(images, proprio, lang)
    logp = laplace_log_prob((mu + 0.1).detach(), mu, beta).sum()
    logp.backward()
    assert m.act.model.encoder_env_state_input_proj.weight.grad.abs().sum() > 0  # through the transformer
    assert m.scale_head[0].weight.grad.abs().sum() > 0
    groups = {g["name"]: g for g in policy_param_groups(m, 1e-5, 1e-4)}
    heads = {id(p) for p in groups["heads"]["params"]}
    assert {id(p) for p in m.action_head.parameters()} | {id(p) for p in m.scale_head.parameters()} == heads
    assert len(groups["backbone"]["params"]) + len(heads) == len([p for p in m.parameters() if p.requires_grad])


def test_the_project_checkpoint_folder_and_lerobots_layout_read_back_the_same_policy(tmp_path):
    from lerobot.policies.act.modeling_act import ACTPolicy

    from worldenv_core.models.checkpoint import load_checkpoint, save_model

    m = policy().train()
    m(*inputs(b=4, seed=2))  # the trainable batch norm's statistics move off the identity
    m.eval()
    m.proprio_norm.set_stats(torch.arange(7.0), torch.full((7,), 2.0))
    m.action_norm.set_stats(torch.ones(7), torch.full((7,), 0.5))
    config = {"_target_": "worldenv_core.models.lerobot_act.ACTLaplacePolicy", **TINY}
    meta = {"kind": "policy", "cameras": ["agentview"], "image_size": 32, "chunk": 4, "action_dim": 7, "proprio_dim": 7}
    save_model(tmp_path / "policy", m, config, meta)
    back, _ = load_checkpoint(tmp_path / "policy", "policy")
    for a, b in zip(back(*inputs()), m(*inputs())):
        assert torch.allclose(a, b, atol=1e-6)
    assert torch.allclose(back.unnormalize_actions(torch.zeros(7)), torch.ones(7))

    lerobot = ACTPolicy.from_pretrained(m.save_lerobot(tmp_path / "lerobot")).eval()  # frozen batch norm, folded
    chunk, _ = lerobot.model(m.inputs(*inputs()))
    assert torch.allclose(chunk, m(*inputs())[0], atol=1e-6)


def test_backbone_weights_come_from_a_local_file_only(tmp_path):
    import torchvision

    torch.manual_seed(1)
    weights = torchvision.models.resnet18(weights=None).state_dict()
    torch.save(weights, tmp_path / "resnet18.pth")
    m = ACTLaplacePolicy(**TINY, backbone_weights=str(tmp_path / "resnet18.pth"))
    assert torch.equal(m.act.model.backbone.state_dict()["conv1.weight"], weights["conv1.weight"])
    torch.save({"unrelated": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(ValueError, match="no weights of ACT's ResNet"):
        ACTLaplacePolicy(**TINY, backbone_weights=str(tmp_path / "other.pth"))


def test_an_untrained_backbone_normalises_with_trainable_batch_norm_and_a_pretrained_one_keeps_frozen(tmp_path):
    """LeRobot's frozen batch norm is the identity on an untrained ResNet, so training could not keep its activations
    in range: untrained, the policy trains batch norm (its statistics follow the data); pretrained, it is LeRobot's."""
    import torchvision
    from torchvision.ops.misc import FrozenBatchNorm2d

    def norms(m):
        return {type(x) for x in m.act.model.backbone.modules() if isinstance(x, (FrozenBatchNorm2d, torch.nn.BatchNorm2d))}

    m = policy().train()
    assert norms(m) == {torch.nn.BatchNorm2d}
    before = m.act.model.backbone.bn1.running_mean.clone()
    m(*inputs())
    assert not torch.equal(before, m.act.model.backbone.bn1.running_mean)
    assert m.act.model.backbone.bn1.weight.requires_grad
    torch.save(torchvision.models.resnet18(weights=None).state_dict(), tmp_path / "resnet18.pth")
    assert norms(ACTLaplacePolicy(**TINY, backbone_weights=str(tmp_path / "resnet18.pth"))) == {FrozenBatchNorm2d}
    assert norms(ACTLaplacePolicy(**TINY, backbone_norm="frozen")) == {FrozenBatchNorm2d}
    with pytest.raises(ValueError, match="policy.backbone_norm must be one of"):
        ACTLaplacePolicy(**TINY, backbone_norm="group")
