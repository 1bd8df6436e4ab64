"""How the policy trains (paper eq. 6 and 8): phase 1 backbone and action head with L1 on mu,
phase 2 the scale head alone with the Laplace NLL on frozen features (the Trainer's two Phases)."""

from __future__ import annotations

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from worldenv_core.models.laplace import laplace_nll
from worldenv_core.training import optimize, random_shift


def _batch_inputs(model, batch, encoder, device, shift: int = 0):
    images = {c: batch["images"][c].to(device) for c in model.cameras}  # (B, 3, H, W) uint8
    if shift:
        images = {c: random_shift(v, shift) for c, v in images.items()}
    return images, batch["proprio"].float().to(device), encoder(list(batch["instruction"])).to(device)


def action_step(model, optimizer, encoder, device, shift: int):
    """Phase 1: backbone and action head, L1 on mu over the chunk's valid steps (eq. 6)."""
    def step(batch) -> dict:
        images, proprio, lang = _batch_inputs(model, batch, encoder, device, shift)
        mu, _ = model(images, proprio, lang)
        target = model.normalize_actions(batch["actions"].float().to(device))
        valid = (~batch["action_is_pad"]).to(device)[..., None].float()
        loss = ((mu - target).abs() * valid).sum() / (valid.sum() * mu.shape[-1])
        optimize(loss, optimizer, clip=1.0, params=list(model.parameters()))
        return {"l1": loss.item()}
    return step


def scale_step(model, optimizer, encoder, device):
    """Phase 2: the scale head alone, Laplace NLL on frozen features and a fixed mu (eq. 8)."""
    def step(batch) -> dict:
        images, proprio, lang = _batch_inputs(model, batch, encoder, device)
        with torch.no_grad():  # features and mu stay fixed: only the scale head learns
            f = model.features(images, proprio, lang)
            mu = model.action_head(f).view(-1, model.chunk, model.action_dim)
        raw = model.scale_head(f).view_as(mu)
        beta = model.beta_min + (model.beta_max - model.beta_min) * torch.sigmoid(raw)
        target = model.normalize_actions(batch["actions"].float().to(device))
        valid = (~batch["action_is_pad"]).to(device)[..., None].float()
        loss = (laplace_nll(target, mu, beta) * valid).sum() / (valid.sum() * mu.shape[-1])
        optimize(loss, optimizer)
        return {"nll": loss.item(), "beta": (beta * valid).sum().item() / (valid.sum().item() * mu.shape[-1])}
    return step


def build_policy(cfg: DictConfig, stats: dict, device) -> tuple[torch.nn.Module, dict, dict]:
    """The policy from its config, normalised by the demos' statistics, and its two optimizers."""
    model_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
    model = instantiate(model_cfg, _convert_="all")
    model.proprio_norm.set_stats(stats["proprio"]["mean"], stats["proprio"]["std"])
    model.action_norm.set_stats(stats["action"]["mean"], stats["action"]["std"])
    model.to(device)
    scale_params = list(model.scale_head.parameters())
    ids = {id(p) for p in scale_params}
    optimizers = {"action": torch.optim.AdamW([p for p in model.parameters() if id(p) not in ids], lr=cfg.train.lr,
                                              weight_decay=cfg.train.weight_decay),
                  "scale": torch.optim.Adam(scale_params, lr=cfg.scale_head.lr)}
    return model, model_cfg, optimizers
