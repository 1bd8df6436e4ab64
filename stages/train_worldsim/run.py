"""Stage `train_worldsim`: the action-conditioned world simulator (paper sec. 4.1, appendix B.2).

Phase 1 trains the autoencoder on frames (L1 + MSE). Every frame is then encoded once, and
phase 2 trains the latent flow model on chunks, with EMA weights; phase 3 (`rollout.steps`)
trains it open loop, on memory it imagined itself. `init_from=` goes on from a trained model with
phase 3 alone. Held-out episodes (every `holdout_every`-th, or the starting model's) measure
fidelity open loop, beside the copy-the-last-frame baseline (and the starting model), and the
kinematic next-state model's error; side-by-side videos (real | imagined) are saved.
"""

from __future__ import annotations

import copy
import json
import logging

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from stages.train_worldsim.evaluation import evaluate_fidelity, write_replays
from stages.train_worldsim.training import ae_phase, episode_chunks, flow_phase, rollout_phase
from worldenv_core.contract import TaskContract
from worldenv_core.data.selection import collected_episodes, episode_key, load_split
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import NextStateModel
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import load_checkpoint, read_config
from worldenv_core.stage import (ConfigError, positive_int, require_task, resolve_checkpoint, resolved, start,
                                 task_contract, work_dir)
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device, trainer_options

log = logging.getLogger("worldenv.train_worldsim")
BATCHES = ("ae.batch_size", "flow.batch_size", "rollout.batch_size")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("ae.steps", "ae.batch_size", "flow.steps", "flow.batch_size", "log_every", "checkpoint_every",
                "holdout_every", "worldsim.sampling_steps"):
        positive_int(cfg, key)
    positive_int(cfg, "rollout.steps", allow_zero=True)
    positive_int(cfg, "rollout.chunks")
    positive_int(cfg, "rollout.batch_size")
    trainer_options(cfg, *BATCHES)
    if cfg.init_from and not cfg.rollout.steps:
        raise ConfigError("init_from trains the open-loop phase only: give it rollout.steps > 0")
    if cfg.camera not in cfg.task.cameras:
        raise ConfigError(f"camera {cfg.camera!r} is not one of the task's cameras {list(cfg.task.cameras)}")
    if not 0.0 <= cfg.flow.ema < 1.0:
        raise ConfigError(f"flow.ema must be in [0, 1), got {cfg.flow.ema}")


def task_cameras(contract: TaskContract, camera: str, task_ids: list[int]) -> dict[int, PinholeCamera]:
    """Each task's camera as the simulator has it (fixtures differ between scenes, cameras may too)."""
    from worldenv_core.envs.libero_env import LiberoEnv

    out = {}
    for tid in task_ids:
        with LiberoEnv(contract.suite, tid, cameras=(), render=False) as env:
            env.reset(init_state=0)
            out[tid] = PinholeCamera.from_sim(env.sim, camera, contract.image_size)
    return out


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    contract = task_contract(cfg)
    device = pick_device(cfg.device)
    config = resolved(cfg)
    tags = {"task": contract.name, "scale": cfg.scale.name, "data": "expert" if cfg.expert_only else "expert+policy"}
    with StageRun(manifest, "train_worldsim", tags, config) as stage:
        base = (resolve_checkpoint(stage, cfg.init_from, "train_worldsim", contract.name, cfg.scale.name)
                if cfg.init_from else None)
        base_model, base_meta = load_checkpoint(base, "worldsim", contract) if base else (None, None)
        paths = collected_episodes(manifest, stage, contract.name, cfg.scale.name, cfg.expert_only)
        if (done := stage.finished_before()) is not None:
            return done.metrics
        _, held, episodes, held_eps = load_split(paths, cfg.holdout_every, cfg.camera,
                                                 base_meta["held_out"] if base else None)
        # named by the split too, so that a work dir and the split its weights were trained on cannot disagree
        work = work_dir(cfg.experiment_dir, "train_worldsim", {**config, "held_out": [episode_key(p) for p in held]},
                        stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        if base:  # its camera models and kinematics are part of what it learned
            cameras = {int(t): PinholeCamera.from_dict(c) for t, c in base_meta["cameras"].items()}
            kinematics = NextStateModel(**base_meta["kinematics"])
        else:
            cameras = task_cameras(contract, cfg.camera, sorted({ep.meta.task_id for ep in episodes + held_eps}))
            kinematics = NextStateModel.fit(episodes)
            log.info("kinematics fitted on %d episodes: %s", len(episodes), kinematics)

        model_cfg = read_config(base)["model"] if base else OmegaConf.to_container(cfg.worldsim, resolve=True)
        model = (copy.deepcopy(base_model) if base else instantiate(model_cfg, _convert_="all")).to(device)
        ema = copy.deepcopy(model).requires_grad_(False)
        optimizers = {"ae": torch.optim.AdamW(model.autoencoder.parameters(), lr=cfg.ae.lr),
                      "flow": torch.optim.AdamW(model.velocity.parameters(), lr=cfg.flow.lr)}
        meta = {"kind": "worldsim", **contract.meta(), "camera": cfg.camera, "kinematics": kinematics.to_dict(),
                "cameras": {str(t): c.to_dict() for t, c in cameras.items()}, "episodes": len(episodes),
                "expert_only": bool(cfg.expert_only), "held_out": [episode_key(p) for p in held],
                "rollout_steps": int(cfg.rollout.steps), **({"init_from_step": base_meta.get("step")} if base else {})}
        trainer = Trainer(work, model, optimizers, model_config=model_cfg, meta=meta, desc="train_worldsim",
                          log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                          extra_state=lambda: {"ema": ema.state_dict()},
                          tracker=make_tracker(cfg.get("logger"), work, "train_worldsim", contract.name, config),
                          **trainer_options(cfg, *BATCHES))
        if "ema" in trainer.extra:
            ema.load_state_dict(trainer.extra["ema"])
        frames_of = lambda: torch.cat([torch.from_numpy(ep.images[cfg.camera]) for ep in episodes])  # noqa: E731
        phases = [] if base else [ae_phase(model, optimizers["ae"], frames_of, cfg, device),
                                  flow_phase(model, ema, optimizers["flow"], episodes, cameras, cfg, device)]
        if cfg.rollout.steps:
            chunks_of = lambda ahead: episode_chunks(model, episodes, device, fresh=False, chunks_ahead=ahead)  # noqa: E731
            phases.append(rollout_phase(model, ema, optimizers["flow"], chunks_of, cameras, cfg, device))
        log.info("training on %d episodes (%d held out): %s on %s; work dir %s", len(episodes), len(held_eps),
                 " + ".join(f"{p.steps} {p.name}" for p in phases), device, work)
        trainer.fit(phases)
        final = trainer.save_final(work / "worldsim", model=ema)
        report = evaluate_fidelity(cfg, ema, kinematics, cameras, held_eps, work, baseline=base_model)
        trainer.tracker.log({f"{k}_h{h}": v[k] for h, v in report["fidelity"].items()
                             for k in ("model_psnr", "model_ssim", "copy_psnr", "copy_ssim")}, trainer.step, group="eval")
        trainer.finish(stage, final, f"train_worldsim {contract.name}")  # closes the tracker: after the eval curves
        for name in ("fidelity.json", "fidelity.md"):
            stage.add_output(work / name, kind="report")
        for video in sorted((work / "videos").glob("*.gif")):
            stage.add_output(video, kind="video")
        for replay in write_replays(ema, kinematics, cameras, held_eps[: cfg.fidelity.videos], work / "imagined",
                                    {"worldsim": str(final)}, cfg.seed):
            stage.add_output(replay, kind="imagined")
        stage.metrics.update({"episodes": len(episodes), "held_out": len(held_eps), "steps": trainer.step,
                              "train_wall_s": round(trainer.wall_s, 1), "device": str(device), **report})
        log.info("world simulator saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics
