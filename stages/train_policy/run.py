"""Stage `train_policy`: supervised fine-tuning of the Laplace policy on expert demonstrations.

Phase 1 trains backbone + action head with L1 on mu (paper eq. 6). Phase 2 trains the scale head
alone with the Laplace NLL (eq. 8) on frozen features and a fixed mu: batch 8, lr 5e-4, 1000
iterations (appendix B.1).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from worldenv_core.data.dataset import EpisodeDataset
from worldenv_core.data.mcap_io import read_info
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import save_model
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.rl.laplace import laplace_nll
from worldenv_core.stage import ConfigError, positive_int, require_task, resolved, start, work_dir
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Checkpoints, RunningMeans, batches, pick_device, plot_history, random_shift

log = logging.getLogger("worldenv.train_policy")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("demos_per_task", "train.steps", "train.batch_size", "scale_head.steps", "scale_head.batch_size",
                "train.log_every", "train.checkpoint_every"):
        positive_int(cfg, key)


def select_demos(paths: list[Path], per_task: int, task_ids: list[int] | None) -> list[Path]:
    """The first `per_task` episodes of every task (by file name, so the choice is stable)."""
    by_task: dict[int, list[Path]] = defaultdict(list)
    for p in sorted(paths):
        meta = read_info(p).meta
        if meta.success:
            by_task[meta.task_id].append(p)
    wanted = task_ids if task_ids is not None else sorted(by_task)
    short = {t: len(by_task.get(t, [])) for t in wanted if len(by_task.get(t, [])) < per_task}
    if short:
        raise ConfigError(f"demos_per_task={per_task}, but the demonstrations have only {short} "
                          "(task: count); collect more with `python -m stages.collect ... episodes_per_task=N`")
    return [p for t in wanted for p in by_task[t][:per_task]]


def _batch_inputs(model, batch, encoder, device, shift: int = 0):
    images = {c: batch["images"][c].to(device) for c in model.cameras}  # (B, 3, H, W) uint8
    if shift:
        images = {c: random_shift(v, shift) for c, v in images.items()}
    return images, batch["proprio"].float().to(device), encoder(list(batch["instruction"])).to(device)


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task = cfg.task
    device = pick_device(cfg.device)
    tags = {"task": task.name, "scale": cfg.scale.name}
    config = resolved(cfg)
    with StageRun(manifest, "train_policy", tags, config) as stage:
        demos = manifest.get(cfg.demos) if cfg.demos else manifest.latest("collect", task=task.name,
                                                                            scale=cfg.scale.name, source="expert")
        paths = select_demos(stage.use(demos, kind="episodes"), cfg.demos_per_task, list(task.task_ids or []) or None)
        work = work_dir(cfg.experiment_dir, "train_policy", config, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        data = EpisodeDataset(paths, cameras=list(task.cameras), mode="chunk", chunk=task.chunk, future_frames=False)
        stats = data.compute_stats()
        model_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
        model = instantiate(model_cfg, _convert_="all")
        model.proprio_norm.set_stats(stats["proprio"]["mean"], stats["proprio"]["std"])
        model.action_norm.set_stats(stats["action"]["mean"], stats["action"]["std"])
        model.to(device)
        scale_params = list(model.scale_head.parameters())
        ids = {id(p) for p in scale_params}
        opt_action = torch.optim.AdamW([p for p in model.parameters() if id(p) not in ids],
                                       lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
        opt_scale = torch.optim.Adam(scale_params, lr=cfg.scale_head.lr)
        optimizers = {"action": opt_action, "scale": opt_scale}
        ckpts = Checkpoints(work)
        step, history = ckpts.restore(model, optimizers)
        meta = {"kind": "policy", "task": task.name, "suite": task.suite, "cameras": list(task.cameras),
                "image_size": task.image_size, "chunk": task.chunk, "action_dim": task.action_dim,
                "proprio_dim": task.proprio_dim, "demos": len(paths)}
        encoder = InstructionEncoder()
        n_action, total = cfg.train.steps, cfg.train.steps + cfg.scale_head.steps
        log.info("training on %d demos (%d chunks) for %d + %d steps on %s; work dir %s",
                 len(paths), len(data), n_action, cfg.scale_head.steps, device, work)
        action_batches = batches(data, cfg.train.batch_size, cfg.seed, start_step=min(step, n_action))
        scale_batches = batches(data, cfg.scale_head.batch_size, cfg.seed + 1, start_step=max(0, step - n_action))
        t0 = time.perf_counter()
        bar = tqdm(range(step, total), initial=step, total=total, desc="train_policy", dynamic_ncols=True)
        tracker = make_tracker(cfg, work, "train_policy", config)
        running = RunningMeans(history, cfg.train.log_every, bar, tracker)
        for step in bar:
            model.train()
            if step < n_action:
                batch = next(action_batches)
                images, proprio, lang = _batch_inputs(model, batch, encoder, device, cfg.train.augment_shift)
                mu, _ = model(images, proprio, lang)
                target = model.normalize_actions(batch["actions"].float().to(device))
                valid = (~batch["action_is_pad"]).to(device)[..., None].float()
                loss = ((mu - target).abs() * valid).sum() / (valid.sum() * mu.shape[-1])
                opt_action.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                opt_action.step()
                running.add(l1=loss.item())
            else:
                batch = next(scale_batches)
                images, proprio, lang = _batch_inputs(model, batch, encoder, device)
                with torch.no_grad():  # features and mu stay fixed: only the scale head learns
                    f = model.features(images, proprio, lang)
                    mu = model.action_head(f).view(-1, model.chunk, model.action_dim)
                raw = model.scale_head(f).view_as(mu)
                beta = model.beta_min + (model.beta_max - model.beta_min) * torch.sigmoid(raw)
                target = model.normalize_actions(batch["actions"].float().to(device))
                valid = (~batch["action_is_pad"]).to(device)[..., None].float()
                loss = (laplace_nll(target, mu, beta) * valid).sum() / (valid.sum() * mu.shape[-1])
                opt_scale.zero_grad(set_to_none=True)
                loss.backward()
                opt_scale.step()
                running.add(nll=loss.item(), beta=(beta * valid).sum().item() / (valid.sum().item() * mu.shape[-1]))
            done = step + 1
            running.end_step(done, total)
            if done % cfg.train.checkpoint_every == 0 or done == total:
                ckpts.save(done, model, model_cfg, meta, optimizers, history)
        bar.close()
        tracker.close()
        final = save_model(work / "policy", model.cpu(), model_cfg, {**meta, "step": total})
        for f in sorted(final.iterdir()):
            stage.add_output(f, kind="checkpoint")
        plot = plot_history(history, work / "losses.png", f"train_policy {task.name}")
        stage.add_output(plot, kind="plot")
        last_l1 = [h["l1"] for h in history if "l1" in h]
        last_nll = [h for h in history if "nll" in h]
        stage.metrics.update({
            "demos": len(paths), "chunks": len(data), "steps": total, "train_wall_s": round(time.perf_counter() - t0, 1),
            "final_l1": last_l1[-1] if last_l1 else None,
            "final_nll": last_nll[-1]["nll"] if last_nll else None,
            "final_mean_beta": last_nll[-1]["beta"] if last_nll else None,
            "device": str(device),
        })
        log.info("policy saved to %s; metrics %s", final, stage.metrics)
    return stage.metrics
