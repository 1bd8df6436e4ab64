"""How the world simulator trains: phase 1 the autoencoder on frames, phase 2 the latent flow
model on chunks of once-encoded frames with EMA weights, and optionally phase 3 the same flow
model open loop, on memory it imagined itself (the Trainer's Phases)."""

from __future__ import annotations

import copy
from itertools import count
from pathlib import Path

import torch
from hydra.utils import instantiate

from worldenv_core import distributed
from worldenv_core.kinematics.action_map import draw_action_maps_per_rollout, gripper_mask
from worldenv_core.kinematics.arm import SerialArm, skeletons
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.models.checkpoint import save_model
from worldenv_core.models.worldsim_data import LatentChunks, encode_episode_frames
from worldenv_core.training import Phase, batches, optimize, per_step, step_seed


def _maps(b: dict, steps: slice, model, cameras: dict[int, PinholeCamera], device,
          arms: dict[int, SerialArm] | None = None) -> torch.Tensor:
    """The action maps of a batch's `steps`, its items possibly from tasks with different cameras; for a
    model whose maps draw the arm, with the links at the recorded joint angles."""
    points = None
    if model.arm_map:
        if not arms or "joints" not in b:
            raise ValueError("this world model draws the arm's links: training needs each task's arm and the "
                             "episodes' joint angles (a latent pack written before they were kept has none)")
        points = skeletons(b["joints"][:, steps].to(device), [arms[int(t)] for t in b["task_id"]]).float()
    return draw_action_maps_per_rollout(b["proprio"][:, steps].to(device), [cameras[int(t)] for t in b["task_id"]],
                                        model.map_size, points)


def _weights(chunks: LatentChunks, cfg):
    """The items' sampling weights when `demo_share` asks for the demos to be drawn at a set share."""
    share = cfg.get("demo_share")
    return None if share is None else chunks.demo_weights(float(share))


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


def flow_phase(model, ema, optimizer, episodes, cameras, cfg, device, arms=None) -> Phase:
    """Phase 2: the latent flow model on chunks of once-encoded frames, with EMA weights. Entering it
    fresh sets the latent scales and starts the EMA from the trained autoencoder."""
    def draw(start: int):
        chunks = episode_chunks(model, episodes, device, fresh=start == 0)
        if start == 0:
            ema.load_state_dict(model.state_dict())
        return batches(chunks, cfg.flow.batch_size, cfg.seed + 1, start_step=start, weights=_weights(chunks, cfg))

    def step(b) -> dict:
        memory = b["memory"].to(device) / model.latent_scale
        memory = memory + cfg.flow.memory_noise * torch.randn_like(memory)
        maps = _maps(b, slice(None), model, cameras, device, arms)  # drawn where the model runs
        loss = model.flow_loss(memory, maps, b["target"].to(device) / model.latent_scale, b["actions"].to(device),
                               b["valid"].to(device))
        optimize(loss, optimizer, clip=1.0, params=list(model.velocity.parameters()))
        _update_ema(ema, model, cfg.flow.ema)
        return {"flow": loss.item()}
    return Phase("flow", cfg.flow.steps, draw, step)


def rollout_phase(model, ema, optimizer, chunks_of, cameras, cfg, device, arms=None) -> Phase:
    """Phase 3, open-loop training. Imagined rollouts start from real frames and then feed on their
    own predictions, which teacher forcing never shows the model: the arm blurs a little per chunk
    and the blur compounds. Here the model first imagines `depth` chunks of the recorded actions
    itself, exactly as imagination does (its sampler and static snap, no gradient), and the flow
    loss then asks for the next chunk's *real* latents from that imagined memory: it learns to
    pull a drifted rollout back to what the actions do. depth is drawn per step from 0 (the
    teacher-forced loss, which keeps one-chunk accuracy) to `rollout.chunks`.
    `chunks_of(chunks_ahead)` gives the LatentChunks (`episode_chunks` from episodes, or a latent pack's)."""
    ahead = cfg.rollout.chunks + 1

    def draw(start: int):
        chunks = chunks_of(ahead)
        return zip(count(start), batches(chunks, cfg.rollout.batch_size, cfg.seed + 2, start_step=start,
                                         weights=_weights(chunks, cfg)))

    def step(item) -> dict:
        done, b = item
        g = torch.Generator().manual_seed(step_seed(cfg.seed + 2, done))
        depth = int(torch.randint(ahead, (1,), generator=g))
        k, n = model.chunk, (depth + 1) * model.chunk
        maps = _maps(b, slice(0, n), model, cameras, device, arms)
        actions = b["actions"][:, :n].float().to(device)
        if depth == 0:  # teacher forcing: the recorded memory (items carry no "past" when rollout.chunks = 0)
            memory = b["memory"].to(device) / model.latent_scale
        else:
            memory = model.memory(_imagine(model, b["past"].to(device) / model.latent_scale, maps, actions, depth))
        memory = memory + cfg.flow.memory_noise * torch.randn_like(memory)
        last = slice(depth * k, n)
        loss = model.flow_loss(memory, maps[:, last], b["target"][:, last].to(device) / model.latent_scale,
                               actions[:, last], b["valid"][:, last].to(device))
        optimize(loss, optimizer, clip=1.0, params=list(model.velocity.parameters()))
        _update_ema(ema, model, cfg.flow.ema)
        return {"rollout": loss.item(), "rollout_depth": depth}
    return Phase("rollout", cfg.rollout.steps, draw, step)


def refine_phase(model, ema, optimizer, chunks_of, cameras, cfg, device, arms=None) -> Phase:
    """Phase 4, the arm refiner (`WorldSimulator.refiner`) on what imagination decodes. The flow model
    and the autoencoder stay as they are; each step imagines `depth` chunks of the recorded actions
    (0..`refine.chunks`, drawn per step; 0 decodes the real latents), decodes `refine.frames` frames of
    the last chunk and asks the refiner, given those frames' action maps, for the real frames: L1 + MSE, weighted
    `refine.arm_weight` times more inside the gripper's projected region, where the model loses the
    robot. `chunks_of(chunks_ahead)` gives LatentChunks with the real frames ("frames")."""
    ahead = cfg.refine.chunks + 1  # items carry "past" (what imagination starts from) only when wider than a chunk

    def draw(start: int):
        chunks = chunks_of(ahead)
        return zip(count(start), batches(chunks, cfg.refine.batch_size, cfg.seed + 3, start_step=start,
                                         weights=_weights(chunks, cfg)))

    def step(item) -> dict:
        done, b = item
        g = torch.Generator().manual_seed(step_seed(cfg.seed + 3, done))
        depth = int(torch.randint(cfg.refine.chunks + 1, (1,), generator=g))
        k = model.chunk
        n = max(depth, 1) * k
        maps = _maps(b, slice(0, n), model, cameras, device, arms)
        with torch.no_grad():
            if depth == 0:
                z = b["target"][:, :k].to(device) / model.latent_scale
            else:
                z = _imagine(model, b["past"].to(device) / model.latent_scale, maps,
                             b["actions"][:, :n].float().to(device), depth)[:, -k:]
            # a few frames of the chunk (decoding and the full-resolution pass are the cost; the policy reads one)
            pick = torch.randperm(k, generator=g)[:min(k, cfg.refine.frames)].sort().values
            decoded = model.decode(z[:, pick])
        last = (n - k + pick).tolist()
        out = model.refiner(decoded.flatten(0, 1), maps[:, last].flatten(0, 1))
        target = b["frames"][:, last].flatten(0, 1).to(device).float() / 255
        mask = _masks(b["proprio"][:, last].to(device), b["task_id"], cameras, model.image_size).flatten(0, 1)
        valid = b["valid"][:, last].flatten().to(device).float()
        weight = (1 + cfg.refine.arm_weight * mask.float())[:, None] * valid[:, None, None, None]
        err = (out - target).abs() + (out - target).pow(2)
        loss = (err * weight).sum() / (weight.sum() * 3).clamp(min=1)
        optimize(loss, optimizer, clip=1.0, params=list(model.refiner.parameters()))
        _update_ema(ema, model, cfg.flow.ema)
        with torch.no_grad():
            arm = mask[:, None].expand_as(out)
            before = (decoded.flatten(0, 1) - target).abs()[arm].mean()
            after = (out - target).abs()[arm].mean()
        return {"refine": loss.item(), "refine_depth": depth, "arm_l1_decoded": before.item(),
                "arm_l1_refined": after.item()}
    return Phase("refine", cfg.refine.steps, draw, step)


def _imagine(model, past: torch.Tensor, maps: torch.Tensor, actions: torch.Tensor, depth: int) -> torch.Tensor:
    """`depth` open-loop chunks of the recorded actions from the real latents `past`, exactly as imagination
    steps (`next_chunk`: its sampler and static snap, no gradient) -> the history, past then imagined."""
    k, history = model.chunk, past
    for c in range(depth):
        history = torch.cat([history, model.next_chunk(history, past[:, -1], maps[:, c * k:(c + 1) * k],
                                                       actions[:, c * k:(c + 1) * k])], dim=1)
    return history


def _masks(proprio: torch.Tensor, task_ids, cameras: dict[int, PinholeCamera], size: int) -> torch.Tensor:
    """(B, n, 7) states -> (B, n, S, S) bool: the gripper's projected region through each item's camera."""
    out = torch.zeros(*proprio.shape[:2], size, size, dtype=torch.bool, device=proprio.device)
    for tid in {int(t) for t in task_ids}:
        rows = [i for i, t in enumerate(task_ids) if int(t) == tid]
        out[rows] = gripper_mask(proprio[rows].flatten(0, 1), cameras[tid], size).view(len(rows), *out.shape[1:])
    return out


@torch.no_grad()
def _update_ema(ema, model, decay: float) -> None:
    if not distributed.last_micro_batch():  # once per optimizer step, after it
        return
    for pe, p in zip(ema.parameters(), model.parameters()):
        pe.lerp_(p, 1 - decay)
    for be, bm in zip(ema.buffers(), model.buffers()):
        be.copy_(bm)


def episode_chunks(model, episodes, device, fresh: bool, chunks_ahead: int = 1, frames: bool = False) -> LatentChunks:
    """Every frame of `episodes` encoded once by the model's autoencoder, sliced into chunks; `fresh`
    first sets the latent scales from them (entering phase 2); `frames` keeps the real images in the
    items too (the refine phase)."""
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
    images = [torch.from_numpy(ep.images[cam]).permute(0, 3, 1, 2).contiguous() for ep in episodes] if frames else None
    return LatentChunks(latents, episodes, model.memory_offsets, model.chunk, chunks_ahead, images)


def _rebuilt(base, model_cfg: dict, setting: str, value: int, fresh: str, seed: int):
    """-> (config, model): `base` rebuilt with `setting=value`, the parameters under `fresh` newly
    initialised (seeded) and every other weight and buffer base's."""
    cfg = {**model_cfg, setting: int(value)}
    torch.manual_seed(seed)
    model = instantiate(cfg, _convert_="all")
    kept = {k: v for k, v in base.state_dict().items() if not k.startswith(fresh)}
    missing, unexpected = model.load_state_dict(kept, strict=False)
    assert not unexpected and all(k.startswith(fresh) for k in missing), (missing, unexpected)
    return cfg, model


def fresh_velocity(base, model_cfg: dict, width: int, seed: int):
    """-> (config, model): `base` with a newly initialised flow network of `width` (a model-size curve
    on one autoencoder); the autoencoder and the latent and delta scales are base's (the flow works in
    its latent space, which a latent pack holds)."""
    return _rebuilt(base, model_cfg, "width", width, "velocity.", seed)


def with_refiner(base, model_cfg: dict, width: int, seed: int):
    """-> (config, model): `base` with an `ArmRefiner` of `width` after its decoder (its own refiner
    kept when it has one of that width: a refine phase that goes on); everything else is base's."""
    if int(model_cfg.get("refiner_width") or 0) == width:
        return model_cfg, copy.deepcopy(base)
    return _rebuilt(base, model_cfg, "refiner_width", width, "refiner.", seed)


def snapshots(work: Path, ema, model_cfg: dict, meta: dict, prior: int, steps: int, k: int):
    """`after_step` keeping the EMA model at k-1 equal fractions of the run (`snapshot_<step>/`): a
    compute curve from one run. None when k is 1."""
    marks = {round(steps * i / k) for i in range(1, k)}
    if not marks:
        return None

    def after(done: int) -> None:
        if done in marks:
            save_model(Path(work) / f"snapshot_{done}", copy.deepcopy(ema).cpu(), model_cfg,
                       {**meta, "rollout_steps": prior + done, "step": done})
    return after
