"""Image backbones, chosen in the config with `_target_`. Each maps a dict of camera images
(B, 3, H, W) float in [0, 1] plus a conditioning vector (B, C) to features (B, out_dim).

* `SmallConvBackbone`: the default; trains from scratch on 2 CPU cores. FiLM-conditioned on the
  instruction, because libero_goal puts ten tasks in one scene and only the words tell them apart.
* `TimmBackbone`: any timm image model (pretrained weights from a local file, never a hub).
* `HFVisionBackbone`: a Hugging Face transformers vision tower (CLIP, SigLIP, DINOv2 ...) loaded
  with `from_pretrained(<local dir>)`, adapted with LoRA through peft (the paper: rank 32).
* `WorldModelLatentBackbone`: frames seen through a trained world simulator's frozen autoencoder
  (the reflector `worldsim_latent`): real and imagined frames are judged in the world model's space.
"""

from __future__ import annotations

import torch
from torch import nn


class FiLMConvBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, cond_dim: int):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, 3, stride=2, padding=1)
        self.norm = nn.GroupNorm(8, c_out)
        self.film = nn.Linear(cond_dim, 2 * c_out)
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        gamma, beta = self.film(cond).chunk(2, dim=-1)
        h = self.norm(self.conv(x))
        return torch.nn.functional.silu(h * (1 + gamma[..., None, None]) + beta[..., None, None])


class SmallConvBackbone(nn.Module):
    """Per-camera FiLM conv stack with shared weights, spatial-softmax keypoints, concatenated."""

    def __init__(self, cameras: list[str], cond_dim: int, widths=(32, 64, 128, 128), keypoints: int = 32):
        super().__init__()
        self.cameras = list(cameras)
        chans = [3, *widths]
        self.blocks = nn.ModuleList(FiLMConvBlock(a, b, cond_dim) for a, b in zip(chans[:-1], chans[1:]))
        self.to_kp = nn.Conv2d(widths[-1], keypoints, 1)
        self.camera_embed = nn.Parameter(torch.zeros(len(self.cameras), 3, 1, 1))
        self.out_dim = len(self.cameras) * keypoints * 2

    def forward(self, images: dict[str, torch.Tensor], cond: torch.Tensor) -> torch.Tensor:
        feats = []
        for i, cam in enumerate(self.cameras):
            x = images[cam] * 2 - 1 + self.camera_embed[i]
            for block in self.blocks:
                x = block(x, cond)
            feats.append(spatial_softmax(self.to_kp(x)))
        return torch.cat(feats, dim=-1)


def spatial_softmax(x: torch.Tensor) -> torch.Tensor:
    """(B, K, H, W) -> (B, 2K) expected (x, y) of each channel's softmax: where things are."""
    b, k, h, w = x.shape
    attn = torch.softmax(x.flatten(2), dim=-1).view(b, k, h, w)
    ys = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype)
    xs = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype)
    return torch.cat([(attn.sum(2) * xs).sum(-1), (attn.sum(3) * ys).sum(-1)], dim=-1)


class _Pooled(nn.Module):
    """Shared plumbing of the pretrained backbones: ImageNet-style normalisation, per-camera
    features, instruction conditioning by concatenation (the language enters after the tower).
    Subclasses set `self.model` and define `encode(x)`: normalised (B, 3, H, W) -> (B, feat_dim)."""

    mean = (0.485, 0.456, 0.406)
    std = (0.229, 0.224, 0.225)

    def __init__(self, cameras: list[str], feat_dim: int, image_size: int | None):
        super().__init__()
        self.cameras = list(cameras)
        self.image_size = image_size
        self.register_buffer("_mean", torch.tensor(self.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("_std", torch.tensor(self.std).view(1, 3, 1, 1), persistent=False)
        self.out_dim = len(self.cameras) * feat_dim

    def forward(self, images: dict[str, torch.Tensor], cond: torch.Tensor) -> torch.Tensor:
        feats = []
        for cam in self.cameras:
            x = images[cam]
            if self.image_size and x.shape[-1] != self.image_size:
                x = nn.functional.interpolate(x, size=(self.image_size, self.image_size), mode="bilinear",
                                              align_corners=False)
            feats.append(self.encode((x - self._mean) / self._std))
        return torch.cat(feats, dim=-1)


class TimmBackbone(_Pooled):
    """A timm model (`num_classes=0`: pooled features). `checkpoint_path` loads local weights."""

    def __init__(self, cameras: list[str], cond_dim: int, model_name: str = "resnet18",
                 checkpoint_path: str | None = None, image_size: int | None = None, **model_kwargs):
        import timm

        model = timm.create_model(model_name, pretrained=bool(checkpoint_path), num_classes=0,
                                  pretrained_cfg_overlay={"file": checkpoint_path} if checkpoint_path else None,
                                  **model_kwargs)
        super().__init__(cameras, model.num_features, image_size)
        self.model = model

    def encode(self, x):
        return self.model(x)


class HFVisionBackbone(_Pooled):
    """A transformers vision model from a local folder (`save_pretrained` layout), LoRA-adapted.

    `pretrained_path`: folder with config.json + weights. `config` (a dict for the model's
    config class) builds an untrained model instead; tests use it with a tiny config.
    """

    def __init__(self, cameras: list[str], cond_dim: int, pretrained_path: str | None = None,
                 config: dict | None = None, lora_rank: int = 32, lora_alpha: int | None = None,
                 lora_targets: tuple[str, ...] = ("q_proj", "v_proj"), image_size: int | None = None):
        from transformers import AutoConfig, AutoModel

        if pretrained_path:
            model = AutoModel.from_pretrained(pretrained_path, local_files_only=True)
        elif config is not None:
            cfg = dict(config)
            model = AutoModel.from_config(AutoConfig.for_model(cfg.pop("model_type"), **cfg))
        else:
            raise ValueError("HFVisionBackbone needs pretrained_path (a local folder) or config")
        hidden = model.config.hidden_size
        size = image_size or getattr(model.config, "image_size", None)
        super().__init__(cameras, hidden, size)
        if lora_rank:
            from peft import LoraConfig, get_peft_model

            model = get_peft_model(model, LoraConfig(r=lora_rank, lora_alpha=lora_alpha or lora_rank,
                                                     target_modules=list(lora_targets), lora_dropout=0.0))
        self.model = model

    def encode(self, x):
        out = self.model(pixel_values=x)
        pooled = getattr(out, "pooler_output", None)
        return pooled if pooled is not None else out.last_hidden_state.mean(1)


class WorldModelLatentBackbone(nn.Module):
    """A FiLM conv stack with keypoints on the latent of a world simulator's autoencoder (frozen),
    not on pixels. An imagined frame is decoded from such a latent; a real frame encoded by the
    same autoencoder loses the same fine detail, so a head trained on real latents sees imagined
    ones as nearly the same kind of input (the success head "on the world model's latent" of the
    Dreamer line, here as the reflector's frame encoder). The autoencoder's weights come from a
    trained world model through `load_autoencoder` (train_reflector does it, from the world model
    it imagines with) and then travel in the reflector's own checkpoint."""

    def __init__(self, cameras: list[str], cond_dim: int, image_size: int = 128, latent_size: int = 16,
                 latent_channels: int = 4, ae_widths=(32, 64), ae_patch: int = 4, widths=(64, 128), keypoints: int = 32):
        super().__init__()
        from worldenv_core.models.worldsim import Autoencoder

        self.cameras = list(cameras)
        self.autoencoder = Autoencoder(image_size, latent_size, latent_channels, ae_widths, ae_patch).requires_grad_(False)
        self.register_buffer("latent_scale", torch.ones(()))
        chans = [latent_channels, *widths]
        self.blocks = nn.ModuleList(FiLMConvBlock(a, b, cond_dim) for a, b in zip(chans[:-1], chans[1:]))
        self.to_kp = nn.Conv2d(widths[-1], keypoints, 1)
        self.out_dim = len(self.cameras) * keypoints * 2
        self.loaded_from: str | None = None

    def load_autoencoder(self, worldsim_path: str) -> None:
        """Copy in the autoencoder (and latent scale) of the world simulator checkpoint at `worldsim_path`."""
        from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint

        world, _ = load_checkpoint(worldsim_path, "worldsim")
        try:
            self.autoencoder.load_state_dict(world.autoencoder.state_dict())
        except RuntimeError as e:
            raise CheckpointError(f"the world simulator at {worldsim_path} has another autoencoder than the reflector's "
                                  f"worldsim_latent encoder was configured with (its image_size, latent_size, "
                                  f"latent_channels, ae_widths, ae_patch): {e}") from None
        self.latent_scale.copy_(world.latent_scale)
        self.loaded_from = str(worldsim_path)

    def train(self, mode: bool = True):
        super().train(mode)
        self.autoencoder.eval()  # frozen: always the inference-time encoder
        return self

    def requires_grad_(self, requires_grad: bool = True):
        super().requires_grad_(requires_grad)
        self.autoencoder.requires_grad_(False)  # the world model's, never trained here
        return self

    def forward(self, images: dict[str, torch.Tensor], cond: torch.Tensor) -> torch.Tensor:
        feats = []
        for cam in self.cameras:
            with torch.no_grad():
                x = self.autoencoder.encode(images[cam]) / self.latent_scale
            for block in self.blocks:
                x = block(x, cond)
            feats.append(spatial_softmax(self.to_kp(x)))
        return torch.cat(feats, dim=-1)
