"""Stage `train_worldsim`: the action-conditioned world simulator (paper sec. 4.1, appendix B.2).

Phase 1 trains the autoencoder on frames (L1 + MSE). Every frame is then encoded once, and
phase 2 trains the latent flow model on chunks, with EMA weights. Held-out episodes (every
`holdout_every`-th) measure fidelity open loop, beside the copy-the-last-frame baseline, and the
kinematic next-state model's error; side-by-side videos (real | imagined) are saved.
"""

from __future__ import annotations

import copy
import json
import logging
import time
from collections import defaultdict
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from worldenv_core.data.mcap_io import write_imagined_episode
from worldenv_core.envs.imagined import ImaginedSimulator, open_loop_fidelity, replay_from_start
from worldenv_core.kinematics.action_map import draw_action_maps_per_rollout
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import NextStateModel, state_errors
from worldenv_core.data.selection import episode_key, load_split
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import save_model
from worldenv_core.models.worldsim_data import LatentChunks, encode_episode_frames
from worldenv_core.rl.imagined_recording import imagined_replay
from worldenv_core.stage import ConfigError, positive_int, require_task, resolved, start, work_dir
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Checkpoints, RunningMeans, batches, pick_device, plot_history
from worldenv_core.viz import montage_video

log = logging.getLogger("worldenv.train_worldsim")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("ae.steps", "ae.batch_size", "flow.steps", "flow.batch_size", "log_every", "checkpoint_every",
                "holdout_every", "worldsim.sampling_steps"):
        positive_int(cfg, key)
    if cfg.camera not in cfg.task.cameras:
        raise ConfigError(f"camera {cfg.camera!r} is not one of the task's cameras {list(cfg.task.cameras)}")
    if not 0.0 <= cfg.flow.ema < 1.0:
        raise ConfigError(f"flow.ema must be in [0, 1), got {cfg.flow.ema}")


def task_cameras(cfg: DictConfig, task_ids: list[int]) -> dict[int, PinholeCamera]:
    """Each task's camera as the simulator has it (fixtures differ between scenes, cameras may too)."""
    from worldenv_core.envs.libero_env import LiberoEnv

    out = {}
    for tid in task_ids:
        with LiberoEnv(cfg.task.suite, tid, cameras=(), render=False) as env:
            env.reset(init_state=0)
            out[tid] = PinholeCamera.from_sim(env.sim, cfg.camera, cfg.task.image_size)
    return out


def _maps(proprio: torch.Tensor, task_ids, cameras: dict[int, PinholeCamera], size: int) -> torch.Tensor:
    """Action maps for a batch whose items may come from tasks with different cameras."""
    return draw_action_maps_per_rollout(proprio, [cameras[int(t)] for t in task_ids], size)


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task = cfg.task
    device = pick_device(cfg.device)
    config = resolved(cfg)
    tags = {"task": task.name, "scale": cfg.scale.name, "data": "expert" if cfg.expert_only else "expert+policy"}
    with StageRun(manifest, "train_worldsim", tags, config) as stage:
        _, held, episodes, held_eps = load_split(manifest, stage, cfg)
        work = work_dir(cfg.experiment_dir, "train_worldsim", config, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        cameras = task_cameras(cfg, sorted({ep.meta.task_id for ep in episodes + held_eps}))
        kinematics = NextStateModel.fit(episodes)
        log.info("kinematics fitted on %d episodes: %s", len(episodes), kinematics)

        model_cfg = OmegaConf.to_container(cfg.worldsim, resolve=True)
        model = instantiate(model_cfg, _convert_="all").to(device)
        ema = copy.deepcopy(model).requires_grad_(False)
        opt_ae = torch.optim.AdamW(model.autoencoder.parameters(), lr=cfg.ae.lr)
        opt_flow = torch.optim.AdamW(model.velocity.parameters(), lr=cfg.flow.lr)
        optimizers = {"ae": opt_ae, "flow": opt_flow}
        ckpts = Checkpoints(work)
        step, history = ckpts.restore(model, optimizers)
        if "ema" in ckpts.extra:
            ema.load_state_dict(ckpts.extra["ema"])
        meta = {"kind": "worldsim", "task": task.name, "suite": task.suite, "camera": cfg.camera,
                "image_size": task.image_size, "chunk": task.chunk, "action_dim": task.action_dim,
                "kinematics": kinematics.to_dict(), "cameras": {str(t): c.to_dict() for t, c in cameras.items()},
                "episodes": len(episodes), "expert_only": bool(cfg.expert_only),
                "held_out": [episode_key(p) for p in held]}
        n_ae, total = cfg.ae.steps, cfg.ae.steps + cfg.flow.steps
        log.info("training on %d episodes (%d held out) for %d + %d steps on %s; work dir %s",
                 len(episodes), len(held_eps), n_ae, cfg.flow.steps, device, work)
        # every training frame, decoded once (the episodes are in memory already)
        frames = torch.cat([torch.from_numpy(ep.images[cfg.camera]) for ep in episodes]) if step < n_ae else None
        chunks = flow_batches = None
        t0 = time.perf_counter()
        bar = tqdm(range(step, total), initial=step, total=total, desc="train_worldsim", dynamic_ncols=True)
        tracker = make_tracker(cfg, work, "train_worldsim", config)
        running = RunningMeans(history, cfg.log_every, bar, tracker)
        for step in bar:
            model.train()
            if step < n_ae:
                pick = torch.randint(len(frames), (cfg.ae.batch_size,),
                                     generator=torch.Generator().manual_seed(cfg.seed * 1_000_003 + step))
                x = frames[pick].permute(0, 3, 1, 2).contiguous().to(device)  # seeded by step: resumes exactly
                target = x.float() / 255
                recon = model.autoencoder.decode(model.autoencoder.encode(x))
                loss = (recon - target).abs().mean() + (recon - target).pow(2).mean()
                opt_ae.zero_grad(set_to_none=True)
                loss.backward()
                opt_ae.step()
                running.add(ae=loss.item())
            else:
                if chunks is None:  # entering (or resuming in) phase 2: encode every frame once
                    frames = None
                    chunks = _latent_chunks(model, episodes, device, fresh=step == n_ae)
                    if step == n_ae:  # the EMA starts from the trained autoencoder
                        ema.load_state_dict(model.state_dict())
                    flow_batches = batches(chunks, cfg.flow.batch_size, cfg.seed + 1, start_step=step - n_ae)
                b = next(flow_batches)
                memory = b["memory"].to(device) / model.latent_scale
                memory = memory + cfg.flow.memory_noise * torch.randn_like(memory)
                maps = _maps(b["proprio"], b["task_id"], cameras, model.map_size).to(device)
                loss = model.flow_loss(memory, maps, b["target"].to(device) / model.latent_scale,
                                       b["actions"].to(device), b["valid"].to(device))
                opt_flow.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.velocity.parameters(), 1.0)
                opt_flow.step()
                with torch.no_grad():
                    for pe, p in zip(ema.parameters(), model.parameters()):
                        pe.lerp_(p, 1 - cfg.flow.ema)
                    for be, bm in zip(ema.buffers(), model.buffers()):
                        be.copy_(bm)
                running.add(flow=loss.item())
            done = step + 1
            running.end_step(done, total)
            if done % cfg.checkpoint_every == 0 or done == total:
                ckpts.save(done, model, model_cfg, meta, optimizers, history, extra={"ema": ema.state_dict()})
        bar.close()
        train_s = time.perf_counter() - t0
        final = save_model(work / "worldsim", ema.cpu(), model_cfg, {**meta, "step": total})
        for f in sorted(final.iterdir()):
            stage.add_output(f, kind="checkpoint")
        stage.add_output(plot_history(history, work / "losses.png", f"train_worldsim {task.name}"), kind="plot")
        report = evaluate_fidelity(cfg, ema, kinematics, cameras, held_eps, work)
        tracker.log({f"{k}_h{h}": v[k] for h, v in report["fidelity"].items() for k in ("model_psnr", "model_ssim",
                                                                                       "copy_psnr", "copy_ssim")},
                    total, group="eval")
        tracker.close()
        for name in ("fidelity.json", "fidelity.md"):
            stage.add_output(work / name, kind="report")
        for video in sorted((work / "videos").glob("*.gif")):
            stage.add_output(video, kind="video")
        for replay in write_replays(ema, kinematics, cameras, held_eps[: cfg.fidelity.videos], work / "imagined",
                                    {"worldsim": str(final)}, cfg.seed):
            stage.add_output(replay, kind="imagined")
        stage.metrics.update({"episodes": len(episodes), "held_out": len(held_eps), "steps": total,
                              "train_wall_s": round(train_s, 1), "device": str(device), **report})
        log.info("world simulator saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics


def _fidelity(cfg, model, kinematics, cameras, held_eps, detail_gate: float) -> tuple[dict, list]:
    """horizon -> metrics averaged over all starts of all held-out tasks; side-by-side videos."""
    by_task = defaultdict(list)
    for ep in held_eps:
        by_task[ep.meta.task_id].append(ep)
    per_task, videos = [], []
    g = torch.Generator().manual_seed(cfg.seed)
    for tid, eps in sorted(by_task.items()):
        sim = ImaginedSimulator(model, kinematics, cameras[tid], detail_gate=detail_gate)
        out = open_loop_fidelity(sim, eps, tuple(cfg.fidelity.horizons), cfg.fidelity.starts_per_episode,
                                 camera=cfg.camera, generator=g)
        per_task.append(out["horizons"])
        videos += out["videos"]
    fidelity = {}
    for h in cfg.fidelity.horizons:
        parts = [r[h] for r in per_task if r[h]["n"]]
        n = sum(p["n"] for p in parts)
        if n:
            fidelity[h] = {k: _weighted_mean([(p[k], p["n"]) for p in parts]) for k in parts[0] if k != "n"} | {"n": n}
    return fidelity, videos


def write_replays(model, kinematics, cameras, episodes, out_dir: Path, extra: dict, seed: int) -> list[Path]:
    """Held-out episodes replayed open loop by the world model from their first frame, each written
    as an imagined episode with the real one beside it under `/real` (Foxglove:
    foxglove/imagined_vs_real.json shows both)."""
    g = torch.Generator().manual_seed(seed + 1)  # its own noise: the fidelity figures stay as they were
    paths = []
    for i, ep in enumerate(episodes):
        sim = ImaginedSimulator(model, kinematics, cameras[ep.meta.task_id])
        (frames, proprio), = replay_from_start(sim, [ep], camera=ep.meta.cameras[0], generator=g, with_proprio=True)
        imagined = imagined_replay(ep, frames, proprio, extra)
        paths.append(write_imagined_episode(out_dir / f"heldout_{i:02d}_task{ep.meta.task_id:02d}.mcap", imagined,
                                            real=ep))
    return paths


def _weighted_mean(values_weights) -> float:
    """Mean over tasks weighted by their sample counts, skipping tasks without a value (nan: e.g.
    no moving region at that horizon)."""
    pairs = [(v, w) for v, w in values_weights if v == v]
    return sum(v * w for v, w in pairs) / sum(w for _, w in pairs) if pairs else float("nan")


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


def evaluate_fidelity(cfg, model, kinematics, cameras, held_eps, work: Path) -> dict:
    """Open-loop fidelity on held-out episodes (model vs copy-last-frame) and kinematics error.
    With detail transfer on, the model's plain decoding is measured too (`plain_psnr/ssim`)."""
    model.eval()
    fidelity, videos = _fidelity(cfg, model, kinematics, cameras, held_eps, model.detail_gate)
    if model.detail_gate > 0:
        plain, _ = _fidelity(cfg, model, kinematics, cameras, held_eps, 0.0)
        for h, v in fidelity.items():
            v.update(plain_psnr=plain[h]["model_psnr"], plain_ssim=plain[h]["model_ssim"])
    kin = {f"kinematics_{h}step": state_errors(kinematics, held_eps, h) for h in (1, cfg.task.chunk)}
    (work / "videos").mkdir(exist_ok=True)
    for i, (real, fake) in enumerate(videos[: cfg.fidelity.videos]):
        n = min(len(real), len(fake))
        side = torch.cat([real[:n], fake[:n]], dim=-1).permute(0, 2, 3, 1).numpy()
        montage_video([side], work / "videos" / f"real_vs_imagined_{i}.gif", max_frames=n)
    report = {"fidelity": {str(h): v for h, v in sorted(fidelity.items())}, **kin,
              "beats_copy_baseline": bool(fidelity) and all(v["model_psnr"] > v["copy_psnr"] for v in fidelity.values()),
              "beats_copy_baseline_ssim": bool(fidelity) and all(v["model_ssim"] > v["copy_ssim"] for v in fidelity.values())}
    (work / "fidelity.json").write_text(json.dumps(report, indent=2))
    plain = lambda v, k: f"{v[k]:.3f}" if k in v else "-"  # noqa: E731
    md = ["| horizon (steps) | PSNR model | PSNR copy-last | SSIM model | SSIM copy-last | PSNR / SSIM plain decoding | "
          "SSIM static: model / copy | SSIM moving: model / copy | moving share | n |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {h} | {v['model_psnr']:.2f} | {v['copy_psnr']:.2f} | {v['model_ssim']:.3f} | {v['copy_ssim']:.3f} | "
           f"{plain(v, 'plain_psnr')} / {plain(v, 'plain_ssim')} | {v['model_ssim_static']:.3f} / "
           f"{v['copy_ssim_static']:.3f} | {v['model_ssim_moving']:.3f} / {v['copy_ssim_moving']:.3f} | "
           f"{v['moving_fraction']:.2f} | {v['n']} |" for h, v in sorted(fidelity.items())]
    md += ["", "| kinematics | pos median (mm) | pos p90 (mm) | rot median (deg) | gripper MAE |", "|---|---|---|---|---|"]
    md += [f"| {v['horizon']} step(s) | {v['pos_mm_median']:.2f} | {v['pos_mm_p90']:.2f} | {v['rot_deg_median']:.2f} | "
           f"{v['grip_mae']:.3f} |" for v in kin.values()]
    (work / "fidelity.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return report
