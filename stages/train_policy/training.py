"""How the policy trains (paper eq. 6 and 8): phase 1 backbone and action head with L1 on mu,
phase 2 the scale head alone with the Laplace NLL on frozen features (the Trainer's two Phases).

Optionally (`train.imagined_proprio`) part of each batch is shown the proprioception imagination
would give it: the kinematic model's state, integrated through the demo's own actions from a frame
up to `train.imagined_proprio_steps` earlier, which drifts from the real one as it does in a
world model's rollout (no contact, no correction). The label stays the demo's action, so the policy
learns to act from what it sees when its sense of its own state is off."""

from __future__ import annotations

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from worldenv_core.kinematics.next_state import NextStateModel
from worldenv_core.models.laplace import laplace_nll
from worldenv_core.training import optimize, random_shift


class ImaginedProprio:
    """Replaces a random `fraction` of a batch's proprio with the kinematic model's open-loop state,
    integrated from 1 to `max_steps` frames back in the same episode (as far as it goes)."""

    def __init__(self, episodes: list, fraction: float, max_steps: int, seed: int):
        self.kinematics = NextStateModel.fit(episodes)
        self.proprio = [torch.as_tensor(ep.proprio, dtype=torch.float64) for ep in episodes]
        self.actions = [torch.as_tensor(ep.actions, dtype=torch.float64) for ep in episodes]
        self.fraction, self.max_steps, self.seed = float(fraction), int(max_steps), int(seed)

    def __call__(self, batch: dict) -> torch.Tensor:
        proprio = batch["proprio"].clone()
        episode, frame = batch["episode_index"].long(), batch["frame_index"].long()
        # drawn from the batch itself, so a resumed run (same batches by step) draws the same
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + int((episode * 100_003 + frame).sum()))
        draw = torch.rand(len(frame), generator=g) < self.fraction
        picked = [i for i in range(len(frame)) if draw[i] and frame[i] > 0]
        if not picked:
            return proprio
        back = [int(torch.randint(1, min(self.max_steps, int(frame[i])) + 1, (), generator=g)) for i in picked]
        k = max(back)
        starts = torch.stack([self.proprio[episode[i]][frame[i] - b] for i, b in zip(picked, back)])
        actions = torch.zeros(len(picked), k, 7, dtype=torch.float64)  # right-aligned: each ends at its frame
        for j, (i, b) in enumerate(zip(picked, back)):
            actions[j, k - b:] = self.actions[episode[i]][frame[i] - b:frame[i]]
        n = len(picked)
        state = starts
        carry = (torch.zeros(n, 3, dtype=torch.float64), torch.zeros(n, 3, dtype=torch.float64),
                 torch.zeros(n, dtype=torch.float64))  # no motion at the start, as a context without its past
        for step in range(k):  # an integration that has not started yet holds its start state
            live = torch.tensor([step >= k - b for b in back])
            nxt, moved = self.kinematics.step(state, actions[:, step], carry)
            state = torch.where(live[:, None], nxt, state)
            carry = tuple(torch.where(live.view(-1, *[1] * (m.dim() - 1)), m, c) for m, c in zip(moved, carry))
        proprio[picked] = state.to(proprio.dtype)
        return proprio


def _batch_inputs(model, batch, encoder, device, shift: int = 0, imagined: ImaginedProprio | None = None):
    images = {c: batch["images"][c].to(device) for c in model.cameras}  # (B, 3, H, W) uint8
    if shift:
        images = {c: random_shift(v, shift) for c, v in images.items()}
    proprio = imagined(batch) if imagined is not None else batch["proprio"]
    return images, proprio.float().to(device), encoder(list(batch["instruction"])).to(device)


def action_step(model, optimizer, encoder, device, shift: int, imagined: ImaginedProprio | None = None):
    """Phase 1: backbone and action head, L1 on mu over the chunk's valid steps (eq. 6)."""
    def step(batch) -> dict:
        images, proprio, lang = _batch_inputs(model, batch, encoder, device, shift, imagined)
        mu, _ = model(images, proprio, lang)
        target = model.normalize_actions(batch["actions"].float().to(device))
        valid = (~batch["action_is_pad"]).to(device)[..., None].float()
        loss = ((mu - target).abs() * valid).sum() / (valid.sum() * mu.shape[-1])
        optimize(loss, optimizer, clip=1.0, params=list(model.parameters()))
        return {"l1": loss.item()}
    return step


def scale_step(model, optimizer, encoder, device, imagined: ImaginedProprio | None = None):
    """Phase 2: the scale head alone, Laplace NLL on frozen features and a fixed mu (eq. 8). The trunk runs in
    eval mode, as in a rollout: a dropout mask (ACT's 0.1) would widen the residuals beta is fitted to, and batch
    norm would go on moving its statistics (and so mu) while the trunk is meant to be frozen."""
    def step(batch) -> dict:
        model.eval()  # the Trainer sets train mode before every step; the scale head has no dropout or norm
        images, proprio, lang = _batch_inputs(model, batch, encoder, device, imagined=imagined)
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
