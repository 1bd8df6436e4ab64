"""The Laplace policy: shapes, learning on real frames, checkpoints, backbones."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.models.checkpoint import CheckpointError, load_model, save_model
from worldenv_core.contract import ContractError
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.models.policy import LaplacePolicy, PolicyRunner

CAMS = ["agentview"]


def small_config(chunk=4, action_dim=7, cameras=CAMS):
    return {"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": cameras, "chunk": chunk,
            "hidden": 64, "instruction_dim": 384, "action_dim": action_dim,
            "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": cameras,
                         "cond_dim": 384, "widths": [8, 16, 16, 16], "keypoints": 8}}


def fake_inputs(b=3, size=32, cams=CAMS):
    g = torch.Generator().manual_seed(0)
    images = {c: torch.randint(0, 255, (b, 3, size, size), generator=g, dtype=torch.uint8) for c in cams}
    return images, torch.randn(b, 7, generator=g), torch.randn(b, 384, generator=g)


def test_heads_have_the_same_shape_and_beta_is_bounded():
    model = instantiate(small_config())
    mu, beta = model(*fake_inputs())
    assert mu.shape == beta.shape == (3, 4, 7)
    assert (beta >= model.beta_min).all() and (beta <= model.beta_max).all()
    assert [p.shape for p in model.action_head.parameters()] == [p.shape for p in model.scale_head.parameters()]


def test_the_rotation_enters_continuously_as_a_matrix():
    """At the gripper-down pose (a half turn about x) the recorded rotation vector jumps between
    about +pi and -pi: as a matrix the policy sees one orientation; as a vector (checkpoints from
    before the option, whose configs lack it) two inputs far apart."""
    images, proprio, instruction = fake_inputs(b=2)
    down = torch.tensor([np.pi - 1e-3, 0.0, 0.02])
    flipped = down - 2 * np.pi * down / down.norm()  # the same rotation, angle 2 pi - |down| about -axis
    proprio[0, 3:6], proprio[1, 3:6] = down, flipped
    torch.manual_seed(0)
    matrix = instantiate({**small_config(), "proprio_rotation": "matrix"}).eval()
    features = matrix.proprio_features(proprio)
    assert features.shape == (2, 10) and torch.allclose(features[0, 3:9], features[1, 3:9], atol=1e-5)
    assert matrix(images, proprio, instruction)[0].shape == (2, 4, 7)
    vector = instantiate(small_config())
    assert vector.proprio_rotation == "vector" and vector.proprio_features(proprio).shape == (2, 7)
    assert (vector.proprio_features(proprio)[0, 3] - vector.proprio_features(proprio)[1, 3]).abs() > 6
    with pytest.raises(Exception, match="proprio_rotation must be one of"):
        instantiate({**small_config(), "proprio_rotation": "quaternion"})


@pytest.mark.sim
def test_a_tiny_policy_overfits_a_handful_of_real_frames(tiny_env):
    """Real LIBERO frames and a real instruction; the action chunk to fit is arbitrary but fixed."""
    from worldenv_core.models.text import InstructionEncoder

    torch.manual_seed(0)
    frames = []
    tiny_env.reset(init_state=0)
    for t in range(6):
        tiny_env.step(np.r_[0.3 * np.sin(t), 0.2, 0, 0, 0, 0, -1])
        f = tiny_env.observe(render=True)
        frames.append(f)
    images = {"agentview": torch.stack([torch.from_numpy(f.images["agentview"]).permute(2, 0, 1) for f in frames])}
    proprio = torch.stack([torch.from_numpy(f.proprio) for f in frames])
    lang = InstructionEncoder()([tiny_env.instruction] * len(frames))
    target = torch.randn(len(frames), 4, 7) * 0.5
    model = instantiate(small_config())
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(300):
        mu, _ = model(images, proprio, lang)
        loss = (mu - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.05, f"could not overfit 6 real frames: L1 {loss.item():.3f}"


def test_checkpoint_round_trip_needs_only_the_folder(tmp_path, contract):
    model = instantiate(small_config())
    model.action_norm.set_stats(np.arange(7), np.full(7, 2.0))
    save_model(tmp_path / "ckpt", model, small_config(), {"kind": "policy", "chunk": 4, "action_dim": 7,
                                                           "cameras": CAMS, "image_size": 32})
    loaded, meta = load_checkpoint(tmp_path / "ckpt", "policy", contract(chunk=4, image_size=32, cameras=tuple(CAMS)))
    inputs = fake_inputs()
    model.eval()
    for a, b in zip(model(*inputs), loaded(*inputs)):
        assert torch.equal(a, b)
    assert torch.equal(loaded.action_norm.mean, torch.arange(7.0))
    assert not (tmp_path / "ckpt.tmp").exists()


def test_bad_checkpoints_give_clear_errors(tmp_path, contract):
    with pytest.raises(CheckpointError, match="not a checkpoint folder"):
        load_checkpoint(tmp_path / "missing", "policy")
    model = instantiate(small_config(action_dim=6))
    save_model(tmp_path / "ckpt6", model, small_config(action_dim=6), {"kind": "policy", "action_dim": 6})
    with pytest.raises(ContractError, match="action_dim=6.*has action_dim=7"):
        load_checkpoint(tmp_path / "ckpt6", "policy", contract())
    wrist = small_config(action_dim=6, cameras=["wrist"])  # made for another camera, consistently
    save_model(tmp_path / "cams", instantiate(wrist), wrist, {"kind": "policy", "cameras": ["wrist"]})
    with pytest.raises(ContractError, match=r"cameras \['wrist'\].*\['agentview'\]"):
        load_checkpoint(tmp_path / "cams", "policy", contract())
    save_model(tmp_path / "edited", model, small_config(action_dim=6), {"kind": "policy", "cameras": ["wrist"]})
    with pytest.raises(CheckpointError, match=r"model.cameras=\['agentview'\] but its meta cameras=\['wrist'\]"):
        load_checkpoint(tmp_path / "edited", "policy", contract())  # one that contradicts itself: named as such
    save_model(tmp_path / "wm", model, small_config(action_dim=6), {"kind": "worldsim"})
    with pytest.raises(CheckpointError, match="not a policy"):
        load_checkpoint(tmp_path / "wm", "policy")


def test_runner_samples_around_mu_and_is_seeded():
    model = instantiate(small_config())
    images, proprio, _ = fake_inputs(b=1)
    obs = {"agentview": images["agentview"][0].permute(1, 2, 0).numpy()}
    mean = PolicyRunner(model, sample=False).act_chunk(obs, proprio[0].numpy(), "pick up the soup")
    a1 = PolicyRunner(model, sample=True, seed=3).act_chunk(obs, proprio[0].numpy(), "pick up the soup")
    a2 = PolicyRunner(model, sample=True, seed=3).act_chunk(obs, proprio[0].numpy(), "pick up the soup")
    assert np.array_equal(a1[0], a2[0]) and not np.array_equal(a1[0], mean[0])
    assert np.array_equal(mean[1], a1[1])  # same mu; only the executed actions differ


def test_timm_backbone_builds_from_config():
    pytest.importorskip("timm")
    cfg = small_config()
    cfg["backbone"] = {"_target_": "worldenv_core.models.backbones.TimmBackbone", "cameras": CAMS, "cond_dim": 384,
                       "model_name": "resnet10t"}
    mu, beta = instantiate(cfg)(*fake_inputs())
    assert mu.shape == (3, 4, 7)


def test_hf_vision_backbone_with_lora_loads_from_a_local_folder(tmp_path):
    """The real loading path (from_pretrained on a local folder) on a tiny CLIP vision tower."""
    from transformers import CLIPVisionConfig, CLIPVisionModel

    tiny = CLIPVisionModel(CLIPVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                            num_attention_heads=2, image_size=32, patch_size=8))
    tiny.save_pretrained(tmp_path / "clip")
    cfg = small_config()
    cfg["backbone"] = {"_target_": "worldenv_core.models.backbones.HFVisionBackbone", "cameras": CAMS,
                       "cond_dim": 384, "pretrained_path": str(tmp_path / "clip"), "lora_rank": 4}
    model = instantiate(cfg)
    trainable = {n for n, p in model.backbone.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n for n in trainable), "only the LoRA adapters of the tower train"
    mu, _ = model(*fake_inputs(size=48))  # resized to the tower's 32 px
    mu.sum().backward()
    save_model(tmp_path / "ckpt", model, cfg, {"kind": "policy"})
    loaded, _ = load_model(tmp_path / "ckpt")
    assert isinstance(loaded, LaplacePolicy)
