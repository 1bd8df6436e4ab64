"""How the world simulator trains: phase 1 the autoencoder on frames, phase 2 the latent flow
model on chunks of once-encoded frames with EMA weights (the Trainer's two Phases)."""

from __future__ import annotations

import torch

from worldenv_core.kinematics.action_map import draw_action_maps_per_rollout
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.models.worldsim_data import LatentChunks, encode_episode_frames
from worldenv_core.training import Phase, batches, optimize, per_step, step_seed


def _maps(proprio: torch.Tensor, task_ids, cameras: dict[int, PinholeCamera], size: int) -> torch.Tensor:
    """Action maps for a batch whose items may come from tasks with different cameras."""
    return draw_action_maps_per_rollout(proprio, [cameras[int(t)] for t in task_ids], size)


def ae_phase(model, optimizer, frames_of, cfg, device) -> Phase:
    """Phase 1: the autoencoder on single frames, L1 + MSE. Frames are drawn by step (resumes exactly);
    `frames_of()` gives every training frame, decoded once, only when the phase runs."""
    def draw(start: int):
        frames = frames_of()
        return per_step(lambda s: frames[torch.randint(len(frames), (cfg.ae.batch_size,),
                                                       generator=torch.Generator().manual_seed(step_seed(cfg.seed, s)))],
                        start)

    def step(x) -> dict:
        x = x.permute(0, 3, 1, 2).contiguous().to(device)
        target = x.float() / 255
        recon = model.autoencoder.decode(model.autoencoder.encode(x))
        loss = (recon - target).abs().mean() + (recon - target).pow(2).mean()
        optimize(loss, optimizer)
        return {"ae": loss.item()}
    return Phase("autoencoder", cfg.ae.steps, draw, step)


def flow_phase(model, ema, optimizer, episodes, cameras, cfg, device) -> Phase:
    """Phase 2: the latent flow model on chunks of once-encoded frames, with EMA weights. Entering it
    fresh sets the latent scales and starts the EMA from the trained autoencoder."""
    def draw(start: int):
        chunks = _latent_chunks(model, episodes, device, fresh=start == 0)
        if start == 0:
            ema.load_state_dict(model.state_dict())
        return batches(chunks, cfg.flow.batch_size, cfg.seed + 1, start_step=start)

    def step(b) -> dict:
        memory = b["memory"].to(device) / model.latent_scale
        memory = memory + cfg.flow.memory_noise * torch.randn_like(memory)
        maps = _maps(b["proprio"], b["task_id"], cameras, model.map_size).to(device)
        loss = model.flow_loss(memory, maps, b["target"].to(device) / model.latent_scale, b["actions"].to(device),
                               b["valid"].to(device))
        optimize(loss, optimizer, clip=1.0, params=list(model.velocity.parameters()))
        with torch.no_grad():
            for pe, p in zip(ema.parameters(), model.parameters()):
                pe.lerp_(p, 1 - cfg.flow.ema)
            for be, bm in zip(ema.buffers(), model.buffers()):
                be.copy_(bm)
        return {"flow": loss.item()}
    return Phase("flow", cfg.flow.steps, draw, step)


def _latent_chunks(model, episodes, device, fresh: bool) -> LatentChunks:
    model.eval()
    cam = next(iter(episodes[0].images))
    latents = [encode_episode_frames(model, ep.images[cam], device=device) for ep in episodes]
    if fresh:  # scales are set once from the trained autoencoder and then saved with the model
        z = torch.cat(latents)
        model.latent_scale.fill_(float(z.std()))
        # the flow's targets are changes from the current latent over 1..K steps
        deltas = torch.cat([(lat[k:] - lat[:-k]).flatten() for lat in latents for k in range(1, model.chunk + 1)
                            if len(lat) > k])
        model.delta_scale.fill_(float(deltas.std() / z.std()))
    return LatentChunks(latents, episodes, model.memory_offsets, model.chunk)
