"""LeRobot's reward classifier (`lerobot.rewards.classifier`, the success detector of its HIL-SERL
recipe) as a reflector: `train_reflector reflector=lerobot_classifier` trains it on the same per-frame
success labels as the project's reflector, and it judges rollouts through the same interface
(`scorer` for growing rollouts, `score_prefixes` for recorded videos), so the paired replays measure
the two side by side.

It is LeRobot's model, unchanged: a ResNet (transformers' `ResNetModel`) per camera, LeRobot's learned
spatial embeddings over the 4 x 4 feature map, a projection and its classifier head, a sigmoid. What
follows from that, and differs from the project's reflector:
* it judges one frame, the newest: it sees no history and no instruction (a task is told apart only
  by what the frame shows);
* its feature map must be 4 x 4, so frames are resized to 128 px (a ResNet's stride is 32);
* LeRobot freezes a pretrained encoder (`lerobot/resnet10`) and trains the head only. Nothing is
  downloaded here: `encoder_path` names a local `save_pretrained` folder of a ResNet, and without one
  the encoder is built untrained from `encoder` (a `ResNetConfig`'s settings) and trained with the
  head (`train_encoder`; LeRobot's own behaviour is `train_encoder=false`).
Frames are normalised with ImageNet's statistics, which is what a pretrained ResNet expects (LeRobot's
processor normalises with the dataset's; for an encoder trained here either works).
"""

from __future__ import annotations

import tempfile

import torch
from torch import nn

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
FEATURE_MAP = 4  # LeRobot's SpatialLearnedEmbeddings is built for a 4 x 4 map: 128 px through stride 32


def build_classifier(camera: str, encoder_path: str | None, encoder: dict | None, hidden_dim: int, latent_dim: int,
                     pooling_dim: int, dropout: float):
    """LeRobot's `Classifier` over one camera, its encoder read from `encoder_path` (local files only) or
    made untrained from `encoder`'s `ResNetConfig` settings (saved to a scratch folder for LeRobot's
    loader, which reads an encoder by name)."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.rewards.classifier.configuration_classifier import RewardClassifierConfig
    from lerobot.rewards.classifier.modeling_classifier import Classifier

    size = 32 * FEATURE_MAP
    features = {f"observation.images.{camera}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, size, size))}

    def make(path: str):
        cfg = RewardClassifierConfig(model_name=path, model_type="cnn", num_cameras=1, hidden_dim=hidden_dim,
                                     latent_dim=latent_dim, image_embedding_pooling_dim=pooling_dim,
                                     dropout_rate=dropout, device="cpu", input_features=features)
        return Classifier(cfg)
    if encoder_path is not None:
        return make(str(encoder_path))
    from omegaconf import OmegaConf
    from transformers import ResNetConfig, ResNetModel

    if OmegaConf.is_config(encoder):  # instantiated without _convert_: transformers' config wants plain lists
        encoder = OmegaConf.to_container(encoder)
    with tempfile.TemporaryDirectory(prefix="resnet-") as scratch:
        ResNetModel(ResNetConfig(**(encoder or {}))).save_pretrained(scratch)
        return make(scratch)


class LeRobotRewardClassifier(nn.Module):
    """LeRobot's reward classifier behind the reflector's interface (module docstring).

    Args:
        camera: the camera it watches (the world simulator's, so imagined video can be judged).
        encoder_path: a local folder of a pretrained ResNet (`save_pretrained`); None: built untrained.
        encoder: `transformers.ResNetConfig` settings of the untrained encoder (ignored with a path).
        train_encoder: train the encoder and LeRobot's spatial embedding with the head (LeRobot: head only).
        max_frames: prefix frames the training sampler hands over; only the newest is judged.
        instruction_dim: the instruction embedding's width (accepted and unused: it sees no instruction).
    """

    reward_kind = "LeRobot reward classifier"

    def __init__(self, camera: str = "agentview", encoder_path: str | None = None, encoder: dict | None = None,
                 train_encoder: bool = True, hidden_dim: int = 256, latent_dim: int = 256, pooling_dim: int = 8,
                 dropout: float = 0.1, max_frames: int = 2, instruction_dim: int = 384):
        super().__init__()
        self.camera, self.max_frames, self.train_encoder = camera, int(max_frames), bool(train_encoder)
        self.input_size = 32 * FEATURE_MAP
        self.classifier = build_classifier(camera, encoder_path, encoder, hidden_dim, latent_dim, pooling_dim, dropout)
        # LeRobot keeps its encoder twice (`encoder`, and inside `encoders[<camera>]`): one module under two
        # names, whose shared tensors safetensors will not write; it stays reachable, registered once
        self.classifier.__dict__["encoder"] = self.classifier._modules.pop("encoder")
        (self.key,) = self.classifier.image_keys
        self.classifier.encoders[self.key].requires_grad_(self.train_encoder)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def logits(self, frames: torch.Tensor) -> torch.Tensor:
        """frames (N, 3, H, W), uint8 or float in [0, 1] -> logits (N,): LeRobot's `predict`, with the
        encoder's gradient kept when it trains (LeRobot's runs it under no_grad)."""
        x = frames.float() / 255.0 if frames.dtype == torch.uint8 else frames.float()
        if x.shape[-1] != self.input_size:
            x = nn.functional.interpolate(x, size=(self.input_size, self.input_size), mode="bilinear",
                                          align_corners=False, antialias=True)
        x = (x - self.mean) / self.std
        with torch.set_grad_enabled(self.train_encoder and torch.is_grad_enabled()):
            feats = self.classifier.encoders[self.key](x)
        return self.classifier.classifier_head(feats).squeeze(-1)

    def forward(self, frames: torch.Tensor, mask: torch.Tensor, instruction: torch.Tensor | None = None) -> torch.Tensor:
        """frames (B, F, 3, H, W) right-padded, mask (B, F) -> logits (B,) of each row's newest frame."""
        newest = mask.sum(1) - 1
        return self.logits(frames[torch.arange(len(frames), device=frames.device), newest])

    @torch.no_grad()
    def probability(self, frames: torch.Tensor) -> torch.Tensor:
        was = self.training
        self.eval()
        try:
            return torch.sigmoid(self.logits(frames))
        finally:
            self.train(was)

    def scorer(self, instructions: list[str], encoder=None) -> "NewestFrameScorer":
        return NewestFrameScorer(self, len(instructions))

    def score_prefixes(self, frames: torch.Tensor, instruction=None, steps=(), encoder=None) -> torch.Tensor:
        """R at each of `steps` of one video: the frame at that step, judged alone."""
        return self.probability(frames[torch.as_tensor(list(steps), device=frames.device)])


class NewestFrameScorer:
    """The `IncrementalScorer` interface for a one-frame judge: keeps the newest frame's score."""

    def __init__(self, model: LeRobotRewardClassifier, batch: int):
        self.model, self.batch, self.last = model, batch, None

    def add(self, frames: torch.Tensor) -> None:
        """frames (B, 3, H, W) for one time step, or (B, n, 3, H, W): only the last is judged."""
        newest = frames if frames.dim() == 4 else frames[:, -1]
        self.last = self.model.probability(newest.to(self.model.mean.device))

    def score(self) -> torch.Tensor:
        if self.last is None:
            raise RuntimeError("add() at least one frame before score()")
        return self.last
