"""A LeRobot ACT policy (Action Chunking Transformer, `lerobot.policies.act`) behind this project's
policy interface (docs/policy_interface.md), so that `train_policy`, `collect source=policy`,
`post_train_loop` and `evaluate` take it as they take `LaplacePolicy`.

ACT decodes a chunk of K actions from K query tokens through a transformer over the image
features, the robot state and (here) the instruction. Its deterministic chunk (the VAE latent at
zero, `use_vae=False`: SFT is the L1 loss on the chunk, as ACT's own without the KL term) is the
Laplace location mu; a scale head on the same decoder tokens gives beta (trained by train_policy's
second phase, as for the project's policy). The instruction embedding enters as ACT's environment
state token, ACT's one vector input besides the robot state (LIBERO's tasks share scenes, so the
policy must know the task). Images are scaled to [0, 1] and by ImageNet's statistics, as
LeRobot's processors do for a ResNet backbone; proprio and actions are normalised by the demos'
statistics held in this module, as for `LaplacePolicy`.

Offline: the ResNet starts from no pretrained weights unless `backbone_weights` names a local
torchvision state-dict file; nothing is fetched. LeRobot's ResNet normalises with frozen batch norm, made
for ImageNet weights: started untrained, its statistics stay the identity, so nothing keeps the activations in
range while it trains. On libero_spatial's demos the layer-4 features grew to about 2e6, the chunk stopped
depending on the image and ACT ended at 0 % (docs/notebook/lerobot_native.md), so an untrained backbone gets
trainable batch norm (`backbone_norm=auto`); LeRobot's layout receives it folded back into frozen batch norm
(the same function in eval mode). `save_lerobot(folder)` also writes the ACT model in
LeRobot's own layout (`ACTPolicy.save_pretrained`), which `ACTPolicy.from_pretrained` reads back.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from worldenv_core.models.policy import Normalizer, mlp, proprio_features
from worldenv_core.robot import ACTION_DIM, PROPRIO_DIM

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
STATE, ENV, IMAGES = "observation.state", "observation.environment_state", "observation.images"


def act_config(cameras: list[str], image_size: int, state_dim: int, instruction_dim: int, action_dim: int,
               chunk: int, **settings):
    """LeRobot's ACTConfig for these inputs: one image feature per camera, the state, the instruction
    as the environment state; no VAE, no pretrained weights fetched."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig

    inputs = {STATE: PolicyFeature(FeatureType.STATE, (state_dim,)),
              ENV: PolicyFeature(FeatureType.ENV, (instruction_dim,)),
              **{f"{IMAGES}.{c}": PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size)) for c in cameras}}
    return ACTConfig(input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
                     chunk_size=chunk, n_action_steps=chunk, use_vae=False, pretrained_backbone_weights=None,
                     device="cpu", push_to_hub=False, **settings)


class ACTLaplacePolicy(nn.Module):
    """Args: cameras, chunk (K), image_size: the task contract's. dim_model, n_heads, dim_feedforward,
    n_encoder_layers, n_decoder_layers, vision_backbone, dropout: ACT's (LeRobot's names).
    backbone_weights: a local torchvision state dict for the ResNet (else it starts untrained).
    backbone_norm: frozen (LeRobot's, for pretrained weights), batch (trainable), auto (batch when untrained).
    beta_min/beta_max: the scale head's log-scale range (soft-clamped), as `LaplacePolicy`'s."""

    def __init__(self, cameras: list[str], chunk: int = 8, image_size: int = 128, instruction_dim: int = 384,
                 proprio_dim: int = PROPRIO_DIM, action_dim: int = ACTION_DIM, proprio_rotation: str = "matrix",
                 dim_model: int = 256, n_heads: int = 8, dim_feedforward: int = 1024, n_encoder_layers: int = 4,
                 n_decoder_layers: int = 1, vision_backbone: str = "resnet18", dropout: float = 0.1,
                 backbone_weights: str | None = None, backbone_norm: str = "auto", scale_layers: int = 2,
                 beta_min: float = -7.0, beta_max: float = 1.0):
        super().__init__()
        from lerobot.policies.act.modeling_act import ACTPolicy

        self.cameras, self.chunk, self.action_dim = list(cameras), int(chunk), int(action_dim)
        self.image_size, self.proprio_rotation = int(image_size), proprio_rotation
        self.beta_min, self.beta_max = float(beta_min), float(beta_max)
        state_dim = proprio_dim + 3 * (proprio_rotation == "matrix")
        self.act = ACTPolicy(act_config(self.cameras, self.image_size, state_dim, instruction_dim, action_dim,
                                        self.chunk, dim_model=dim_model, n_heads=n_heads,
                                        dim_feedforward=dim_feedforward, n_encoder_layers=n_encoder_layers,
                                        n_decoder_layers=n_decoder_layers, vision_backbone=vision_backbone,
                                        dropout=dropout))
        if backbone_weights:
            load_resnet_weights(self.act.model.backbone, backbone_weights)
        if backbone_norm not in BACKBONE_NORMS:
            raise ValueError(f"policy.backbone_norm must be one of {list(BACKBONE_NORMS)}, got {backbone_norm!r}")
        if backbone_norm == "batch" or (backbone_norm == "auto" and not backbone_weights):
            swap_norms(self.act.model.backbone, to_trainable=True)
        self.proprio_norm, self.action_norm = Normalizer(proprio_dim), Normalizer(action_dim)
        self.scale_head = mlp(dim_model, dim_model, action_dim, scale_layers)  # per decoder token, as ACT's action head
        self.register_buffer("image_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("image_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def action_head(self) -> nn.Module:
        """ACT's own head: decoder tokens (B, K, D) -> the chunk (B, K, action_dim)."""
        return self.act.model.action_head

    @property
    def backbone(self) -> nn.Module:
        """What `rl.lr_backbone` trains: everything of ACT but its action head (the ResNet, the
        transformer, the input projections); the rest (action and scale heads) gets `rl.lr_heads`."""
        return nn.ModuleList([m for name, m in self.act.model.named_children() if name != "action_head"])

    def inputs(self, images: dict[str, torch.Tensor], proprio: torch.Tensor, instruction: torch.Tensor) -> dict:
        """ACT's batch: images in [0, 1] by ImageNet's statistics, the normalised state, the instruction."""
        imgs = [(images[c].float() / 255.0 if images[c].dtype == torch.uint8 else images[c].float()) for c in self.cameras]
        return {STATE: proprio_features(proprio, self.proprio_norm, self.proprio_rotation), ENV: instruction.float(),
                IMAGES: [(x - self.image_mean) / self.image_std for x in imgs]}

    def features(self, images, proprio, instruction) -> torch.Tensor:
        """ACT's decoder tokens (B, K, dim_model), what its action head and the scale head read."""
        seen = {}
        hook = self.act.model.action_head.register_forward_hook(lambda m, args, out: seen.setdefault("f", args[0]))
        try:
            self.act.model(self.inputs(images, proprio, instruction))
        finally:
            hook.remove()
        return seen["f"]

    def forward(self, images, proprio, instruction) -> tuple[torch.Tensor, torch.Tensor]:
        """-> mu, beta, each (B, K, action_dim), in normalised action space."""
        f = self.features(images, proprio, instruction)
        mu = self.action_head(f)
        beta = self.beta_min + (self.beta_max - self.beta_min) * torch.sigmoid(self.scale_head(f))
        return mu, beta

    def unnormalize_actions(self, a: torch.Tensor) -> torch.Tensor:
        return self.action_norm.inverse(a)

    def normalize_actions(self, a: torch.Tensor) -> torch.Tensor:
        return self.action_norm(a)

    def save_lerobot(self, folder: str | Path) -> Path:
        """The ACT model in LeRobot's layout (config.json + model.safetensors), for `ACTPolicy.from_pretrained`.
        LeRobot keeps normalisation in its processors: this policy's statistics are in its own checkpoint."""
        import copy

        folder = Path(folder)
        act = copy.deepcopy(self.act).eval()
        swap_norms(act.model.backbone, to_trainable=False)  # LeRobot's ACT builds frozen batch norm
        act.save_pretrained(folder)
        return folder


BACKBONE_NORMS = ("auto", "frozen", "batch")


def swap_norms(module: nn.Module, to_trainable: bool) -> None:
    """In place: every frozen batch norm of `module` as a trainable one with the same statistics (`to_trainable`),
    or back (the statistics the trainable one has learnt, frozen: the same function as it computes in eval mode)."""
    from torchvision.ops.misc import FrozenBatchNorm2d

    for name, child in module.named_children():
        if to_trainable and isinstance(child, FrozenBatchNorm2d):
            new = nn.BatchNorm2d(child.weight.numel(), eps=child.eps)
        elif not to_trainable and isinstance(child, nn.BatchNorm2d):
            new = FrozenBatchNorm2d(child.num_features, eps=child.eps)
        else:
            swap_norms(child, to_trainable)
            continue
        with torch.no_grad():
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(new, key).copy_(getattr(child, key))
        setattr(module, name, new)


def load_resnet_weights(backbone: nn.Module, path: str) -> None:
    """A local torchvision ResNet state dict into ACT's backbone (the layers it keeps); one line if the
    file does not fit."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    mine = backbone.state_dict()
    kept = {k: v for k, v in state.items() if k in mine and mine[k].shape == v.shape}
    if not kept:
        raise ValueError(f"{path} holds no weights of ACT's ResNet backbone (its keys: {sorted(state)[:5]} ...)")
    backbone.load_state_dict(kept, strict=False)
