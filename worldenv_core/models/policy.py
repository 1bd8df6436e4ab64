"""The VLA policy in OpenVLA-OFT's shape (paper appendix B.1, figure 7).

observation (camera images, proprio s_t, instruction g) -> hidden f -> two parallel MLP heads of
the same shape: the action head mu (a chunk of K actions, trained with L1) and the scale head
beta = log b (trained with the Laplace NLL). Actions are sampled from Laplace(mu, exp(beta)).

mu and beta live in normalised action space ((a - mean) / std with dataset statistics stored in
the model), where both losses and all log-probabilities are computed; `unnormalize_actions`
maps back to the simulator's units. The Jacobian of that map is a constant, so PPO ratios are
the same in either space.
"""

from __future__ import annotations

import torch
from torch import nn

from worldenv_core.kinematics.next_state import axis_angle_to_matrix
from worldenv_core.robot import ACTION_DIM, PROPRIO_DIM

ROTATION_INPUTS = ("vector", "matrix")


def mlp(d_in: int, hidden: int, d_out: int, layers: int = 2) -> nn.Sequential:
    mods, d = [], d_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.LayerNorm(hidden), nn.GELU()]
        d = hidden
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


class Normalizer(nn.Module):
    """(x - mean) / std with stats as buffers, so they travel inside the checkpoint."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    def set_stats(self, mean, std, min_std: float = 1e-3) -> None:
        self.mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        # a constant dimension (e.g. an unused rotation axis) must not blow up on division
        self.std.copy_(torch.as_tensor(std, dtype=torch.float32).clamp_min(min_std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean


def proprio_features(proprio: torch.Tensor, norm: Normalizer, rotation: str) -> torch.Tensor:
    """What a policy sees of the proprio: normalised, its rotation vector replaced by the rotation
    matrix's first two columns with `rotation="matrix"` (in [-1, 1]: not normalised)."""
    normed = norm(proprio)
    if rotation == "vector":
        return normed
    columns = axis_angle_to_matrix(proprio[..., 3:6].float())[..., :2].flatten(-2)
    return torch.cat([normed[..., :3], columns, normed[..., 6:]], dim=-1)


class LaplacePolicy(nn.Module):
    """Args:
        backbone: an image backbone (see backbones.py) built for `cameras`.
        chunk: K actions per prediction. hidden: width of f and of both heads.
        beta_min/beta_max: the scale head's log-scale range (soft-clamped), so exploration noise
        can neither vanish nor swamp the action.
        proprio_rotation: how the end-effector's rotation vector (proprio 3:6) enters. "matrix": as
        the first two columns of its rotation matrix, continuous in the orientation. "vector": as
        it is (checkpoints from before this option): its angle is kept in [0, pi], so at LIBERO's
        gripper-down pose (a half turn about x) it jumps between about +pi and -pi with sub-degree
        jitter, 5-11 times in a recorded episode, and a benchmark init state starts on either side.
    """

    def __init__(self, backbone: nn.Module, cameras: list[str], chunk: int = 8, hidden: int = 512,
                 instruction_dim: int = 384, proprio_dim: int = PROPRIO_DIM, action_dim: int = ACTION_DIM,
                 head_layers: int = 2, beta_min: float = -7.0, beta_max: float = 1.0,
                 proprio_rotation: str = "vector"):
        super().__init__()
        if proprio_rotation not in ROTATION_INPUTS:
            raise ValueError(f"proprio_rotation must be one of {ROTATION_INPUTS}, got {proprio_rotation!r}")
        self.proprio_rotation = proprio_rotation
        self.cameras, self.chunk, self.action_dim = list(cameras), int(chunk), int(action_dim)
        self.proprio_dim, self.instruction_dim = int(proprio_dim), int(instruction_dim)
        self.beta_min, self.beta_max = float(beta_min), float(beta_max)
        self.backbone = backbone
        self.proprio_norm = Normalizer(proprio_dim)
        self.action_norm = Normalizer(action_dim)
        # the matrix's 6 entries replace the vector's 3 (they are in [-1, 1]: not normalised)
        self.proprio_proj = nn.Sequential(nn.Linear(proprio_dim + 3 * (proprio_rotation == "matrix"), 64), nn.GELU())
        self.lang_proj = nn.Sequential(nn.Linear(instruction_dim, 128), nn.GELU())
        self.trunk = mlp(backbone.out_dim + 64 + 128, hidden, hidden, layers=1)
        out = self.chunk * self.action_dim
        self.action_head = mlp(hidden, hidden, out, head_layers)
        self.scale_head = mlp(hidden, hidden, out, head_layers)  # same MLP shape as the action head

    def features(self, images: dict[str, torch.Tensor], proprio: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """The hidden state f. images: camera -> (B, 3, H, W) uint8 or float in [0, 1]."""
        imgs = {c: (images[c].float() / 255.0 if images[c].dtype == torch.uint8 else images[c]) for c in self.cameras}
        vis = self.backbone(imgs, instruction)
        return self.trunk(torch.cat([vis, self.proprio_proj(self.proprio_features(proprio)),
                                     self.lang_proj(instruction)], dim=-1))

    def proprio_features(self, proprio: torch.Tensor) -> torch.Tensor:
        return proprio_features(proprio, self.proprio_norm, self.proprio_rotation)

    def forward(self, images, proprio, instruction) -> tuple[torch.Tensor, torch.Tensor]:
        """-> mu, beta, each (B, K, action_dim), in normalised action space."""
        f = self.features(images, proprio, instruction)
        shape = (f.shape[0], self.chunk, self.action_dim)
        mu = self.action_head(f).view(shape)
        raw = self.scale_head(f).view(shape)
        # soft clamp keeps gradients alive at the bounds
        beta = self.beta_min + (self.beta_max - self.beta_min) * torch.sigmoid(raw)
        return mu, beta

    def unnormalize_actions(self, a: torch.Tensor) -> torch.Tensor:
        return self.action_norm.inverse(a)

    def normalize_actions(self, a: torch.Tensor) -> torch.Tensor:
        return self.action_norm(a)


class PolicyRunner:
    """Acts with a policy one chunk at a time: the caller renders only at chunk boundaries.

    sample=False executes mu (evaluation); sample=True draws from Laplace(mu, noise_scale *
    exp(beta)) (exploration data, post-training rollouts). mu and beta are returned in the
    policy's normalised action space, where the log-probabilities are computed."""

    def __init__(self, model: LaplacePolicy, sample: bool = False, noise_scale: float = 1.0, seed: int = 0,
                 device: str = "cpu"):
        from worldenv_core.models.text import InstructionEncoder

        self.model, self.sample, self.noise_scale = model.eval(), sample, float(noise_scale)
        self.device = torch.device(device)
        self.generator = torch.Generator(device=self.device).manual_seed(int(seed))
        self.encoder = InstructionEncoder()

    @property
    def cameras(self) -> list[str]:
        return self.model.cameras

    @torch.no_grad()
    def act_chunk(self, images: dict, proprio, instruction: str):
        """images: camera -> (H, W, 3) uint8 upright. Returns numpy (actions, mu, beta), each (K, 7);
        actions in simulator units."""
        from worldenv_core.models.laplace import laplace_sample

        imgs = {c: torch.as_tensor(images[c]).permute(2, 0, 1)[None].to(self.device) for c in self.cameras}
        prop = torch.as_tensor(proprio, dtype=torch.float32)[None].to(self.device)
        lang = self.encoder([instruction]).to(self.device)
        mu, beta = self.model(imgs, prop, lang)
        a = laplace_sample(mu, beta, self.generator, self.noise_scale) if self.sample else mu
        actions = self.model.unnormalize_actions(a)
        return actions[0].cpu().numpy(), mu[0].cpu().numpy(), beta[0].cpu().numpy()
