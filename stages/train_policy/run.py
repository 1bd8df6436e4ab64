"""Stage `train_policy`: supervised fine-tuning of the Laplace policy on expert demonstrations.

Phase 1 trains backbone + action head with L1 on mu (paper eq. 6). Phase 2 trains the scale head
alone with the Laplace NLL (eq. 8) on frozen features and a fixed mu: batch 8, lr 5e-4, 1000
iterations (appendix B.1).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from pathlib import Path

from omegaconf import DictConfig

from stages.train_policy.training import ImaginedProprio, action_step, build_policy, scale_step
from worldenv_core.data.dataset import EpisodeDataset
from worldenv_core.data.mcap_io import read_info
from worldenv_core.manifest import StageRun
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.stage import ConfigError, positive_int, require_task, resolved, start, task_contract, work_dir
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Phase, Trainer, batches, pick_device, trainer_options

log = logging.getLogger("worldenv.train_policy")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("demos_per_task", "train.steps", "train.batch_size", "scale_head.steps", "scale_head.batch_size",
                "train.log_every", "train.checkpoint_every"):
        positive_int(cfg, key)
    trainer_options(cfg, "train.batch_size", "scale_head.batch_size")
    if not 0.0 <= cfg.train.imagined_proprio <= 1.0:
        raise ConfigError(f"train.imagined_proprio is a fraction of each batch in [0, 1], got {cfg.train.imagined_proprio}")
    positive_int(cfg, "train.imagined_proprio_steps")


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


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    contract = task_contract(cfg)
    device = pick_device(cfg.device)
    config = resolved(cfg)
    with StageRun(manifest, "train_policy", {"task": contract.name, "scale": cfg.scale.name}, config) as stage:
        demos = manifest.get(cfg.demos) if cfg.demos else manifest.latest("collect", task=contract.name,
                                                                            scale=cfg.scale.name, source="expert")
        paths = select_demos(stage.use(demos, kind="episodes"), cfg.demos_per_task, list(contract.task_ids or []) or None)
        key = config
        if not cfg.train.imagined_proprio:  # added later: off keeps earlier work dirs
            key = {**config, "train": {k: v for k, v in config["train"].items() if not k.startswith("imagined_proprio")}}
        if (done := stage.finished_before()) is not None:
            return done.metrics
        work = work_dir(cfg.experiment_dir, "train_policy", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        data = EpisodeDataset(paths, cameras=list(contract.cameras), mode="chunk", chunk=contract.chunk,
                              future_frames=False)
        model, model_cfg, optimizers = build_policy(cfg, data.compute_stats(), device)
        trainer = Trainer(work, model, optimizers, model_config=model_cfg, desc="train_policy",
                          meta={"kind": "policy", **contract.meta(), "cameras": list(contract.cameras),
                                "demos": len(paths)},
                          log_every=cfg.train.log_every, checkpoint_every=cfg.train.checkpoint_every,
                          tracker=make_tracker(cfg.get("logger"), work, "train_policy", contract.name, config),
                          **trainer_options(cfg, "train.batch_size", "scale_head.batch_size"))
        encoder = InstructionEncoder()
        imagined = (ImaginedProprio([data.get_episode(i) for i in range(data.num_episodes)], cfg.train.imagined_proprio,
                                    cfg.train.imagined_proprio_steps, cfg.seed) if cfg.train.imagined_proprio else None)
        log.info("training on %d demos (%d chunks) for %d + %d steps on %s; work dir %s",
                 len(paths), len(data), cfg.train.steps, cfg.scale_head.steps, device, work)
        trainer.fit([
            Phase("action", cfg.train.steps, lambda s: batches(data, cfg.train.batch_size, cfg.seed, start_step=s),
                  action_step(model, optimizers["action"], encoder, device, cfg.train.augment_shift, imagined)),
            Phase("scale", cfg.scale_head.steps, lambda s: batches(data, cfg.scale_head.batch_size, cfg.seed + 1, start_step=s),
                  scale_step(model, optimizers["scale"], encoder, device, imagined))])
        final = trainer.save_final(work / "policy")
        trainer.finish(stage, final, f"train_policy {contract.name}")
        last = lambda key: next((h[key] for h in reversed(trainer.history) if key in h), None)  # noqa: E731
        stage.metrics.update({"demos": len(paths), "chunks": len(data), "steps": trainer.step,
                              "train_wall_s": round(trainer.wall_s, 1), "final_l1": last("l1"),
                              "final_nll": last("nll"), "final_mean_beta": last("beta"), "device": str(device)})
        log.info("policy saved to %s; metrics %s", final, stage.metrics)
    return stage.metrics
