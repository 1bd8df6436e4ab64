"""LeRobot's reward classifier as a reflector: LeRobot's own model inside (its head and encoder give
the same logits as LeRobot's `predict`), judging the newest frame, trainable from scratch when no
pretrained encoder is given, saved and loaded through the project's checkpoints, nothing downloaded."""
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.models.checkpoint import load_model, save_model

CONFIG = {"_target_": "worldenv_core.models.lerobot_reward.LeRobotRewardClassifier", "camera": "agentview",
          "encoder": {"embedding_size": 8, "hidden_sizes": [8, 16, 16, 16], "depths": [1, 1, 1, 1],
                      "layer_type": "basic"},
          "hidden_dim": 16, "latent_dim": 16, "pooling_dim": 2}


def frames(n, size=64, seed=0):
    return torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8, generator=torch.Generator().manual_seed(seed))


def test_it_is_lerobots_classifier_judging_the_newest_frame():
    model = instantiate(CONFIG).eval()
    x = frames(3)
    native = model.classifier.predict([(torch.nn.functional.interpolate(x.float() / 255, size=(128, 128),
                                                                        mode="bilinear", antialias=True)
                                        - model.mean) / model.std])
    torch.testing.assert_close(model.probability(x), native.probabilities, rtol=1e-4, atol=1e-5)
    video = torch.stack([x, frames(3, seed=1)], dim=1)  # (B, F=2, ...)
    mask = torch.tensor([[True, True], [True, False], [True, True]])
    newest = torch.stack([video[0, 1], video[1, 0], video[2, 1]])
    torch.testing.assert_close(torch.sigmoid(model(video, mask)), model.probability(newest))
    scores = model.score_prefixes(x, "any instruction", [0, 2])
    torch.testing.assert_close(scores, model.probability(x[[0, 2]]))
    scorer = model.scorer(["a", "b", "c"])
    with pytest.raises(RuntimeError, match="add"):
        scorer.score()
    scorer.add(video)  # a chunk of frames: the last is judged
    torch.testing.assert_close(scorer.score(), model.probability(video[:, -1]))


def test_the_untrained_encoder_trains_with_the_head_and_lerobots_frozen_mode_trains_the_head_only():
    for train_encoder in (True, False):
        model = instantiate({**CONFIG, "train_encoder": train_encoder})
        video, mask = frames(4)[:, None], torch.ones(4, 1, dtype=torch.bool)
        torch.nn.functional.binary_cross_entropy_with_logits(model(video, mask), torch.tensor([0.0, 1, 0, 1])).backward()
        enc = model.classifier.encoders[model.key]
        assert all(p.grad is not None for p in model.classifier.classifier_head.parameters())
        assert (enc[0].embedder.embedder.convolution.weight.grad is not None) == train_encoder
        assert any(p.requires_grad for p in enc.parameters()) == train_encoder


def test_a_checkpoint_round_trip_keeps_every_weight_and_the_verdicts(tmp_path):
    model = instantiate(CONFIG).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))  # not what a fresh build would have
    saved = save_model(tmp_path / "reflector", model, CONFIG, {"kind": "reflector"})
    back, _ = load_model(saved)
    torch.testing.assert_close(back.eval().probability(frames(2)), model.probability(frames(2)))


def test_a_local_pretrained_encoder_is_read_from_its_folder(tmp_path):
    from transformers import ResNetConfig, ResNetModel

    encoder = ResNetModel(ResNetConfig(**CONFIG["encoder"]))
    encoder.save_pretrained(tmp_path / "resnet")
    model = instantiate({**CONFIG, "encoder_path": str(tmp_path / "resnet"), "train_encoder": False})
    for mine, theirs in zip(model.classifier.encoder.state_dict().values(), encoder.state_dict().values()):
        torch.testing.assert_close(mine, theirs)
