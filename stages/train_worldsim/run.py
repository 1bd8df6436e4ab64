"""Stage `train_worldsim`: the action-conditioned world simulator (paper sec. 4.1, appendix B.2).

Phase 1 trains the autoencoder on frames (L1 + MSE). Every frame is then encoded once, and
phase 2 trains the latent flow model on chunks, with EMA weights; phase 3 (`rollout.steps`)
trains it open loop, on memory it imagined itself. `init_from=` goes on from a trained model with
phase 3 alone. Held-out episodes (every `holdout_every`-th, or the starting model's) measure
fidelity open loop, beside the copy-the-last-frame baseline (and the starting model), and the
kinematic next-state model's error; side-by-side videos (real | imagined) are saved.

On a GPU host without the episodes or the simulator, phase 3 runs from a latent pack:
`init_from=<model> latents_to=<pack>` here writes the model's training set as its latents, and
`init_from=<model> latents_from=<pack> minutes=6` there trains on it (docs/world_simulator.md).
"""

from __future__ import annotations

import copy
import json
import logging
import time

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from stages.train_worldsim.evaluation import evaluate_fidelity, write_replays
from stages.train_worldsim.training import (ae_phase, episode_chunks, flow_phase, fresh_velocity, refine_phase,
                                            rollout_phase, snapshots, with_refiner)
from worldenv_core.contract import TaskContract
from worldenv_core.data.selection import POLICY_COLLECTIONS, collected_episodes, episode_key, load_split
from worldenv_core.envs.scene_geometry import scenes_file, task_scenes
from worldenv_core.kinematics.arm import SerialArm
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import NextStateModel
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import load_checkpoint, read_config
from worldenv_core.models.latent_pack import read_latent_pack, write_latent_pack
from worldenv_core.models.worldsim_data import encode_episode_frames
from worldenv_core.stage import (ConfigError, one_of, positive_int, require_task, resolve_checkpoint, resolved, start,
                                 task_contract, work_dir)
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device, planned_steps, planned_total, trainer_options

log = logging.getLogger("worldenv.train_worldsim")
BATCHES = ("ae.batch_size", "flow.batch_size", "rollout.batch_size")
ON_A_MODEL = ("latents_to", "latents_from", "fresh_width", "minutes")  # settings that go on from init_from's model
# settings added after runs were made: at these values a run keeps its record's settings hash and work dir
LATER_DEFAULTS = {"latents_to": None, "latents_from": None, "latents_every": 1, "fresh_width": None, "minutes": None,
                  "snapshots": 1, "policy_collections": "latest", "demo_share": None,
                  "refine": {"steps": 0, "chunks": 3, "batch_size": 8, "frames": 2, "lr": 1e-3, "arm_weight": 4.0, "width": 16}}


def validate(cfg: DictConfig) -> None:
    require_task(cfg, registry=not cfg.latents_from)
    for key in ("ae.steps", "ae.batch_size", "flow.steps", "flow.batch_size", "log_every", "checkpoint_every",
                "holdout_every", "worldsim.sampling_steps", "latents_every", "snapshots"):
        positive_int(cfg, key)
    positive_int(cfg, "rollout.steps", allow_zero=True)
    positive_int(cfg, "rollout.chunks", allow_zero=True)  # 0: teacher-forced, e.g. a fresh flow network first
    one_of(cfg, "policy_collections", POLICY_COLLECTIONS)
    positive_int(cfg, "rollout.batch_size")
    for key in ("refine.steps", "refine.chunks"):
        positive_int(cfg, key, allow_zero=True)
    for key in ("refine.batch_size", "refine.frames", "refine.width"):
        positive_int(cfg, key)
    share = cfg.get("demo_share")
    if share is not None and not (isinstance(share, (int, float)) and 0 < share < 1):
        raise ConfigError(f"demo_share must be a number strictly between 0 and 1 (or null), got {share!r}")
    if share is not None and cfg.expert_only:
        raise ConfigError("demo_share weighs the demos against the policy rollouts: expert_only=true trains on no rollouts")
    if cfg.refine.arm_weight < 0:
        raise ConfigError(f"refine.arm_weight must be >= 0, got {cfg.refine.arm_weight}")
    if cfg.refine.steps and not cfg.init_from:
        raise ConfigError("refine.steps trains the arm refiner on a trained model's imagined frames: "
                          "give init_from=<record or folder>")
    if cfg.refine.steps and cfg.latents_from:
        raise ConfigError("refine.steps learns from the real frames, which a latent pack does not hold: "
                          "run it where the episodes are")
    trainer_options(cfg, *BATCHES)
    given = [k for k in ON_A_MODEL if cfg.get(k) is not None]
    if given and not cfg.init_from:
        raise ConfigError(f"{given[0]} goes on from a trained model (its autoencoder): give init_from=<record or folder>")
    if cfg.snapshots > 1 and not cfg.init_from:
        raise ConfigError("snapshots keeps the model at fractions of the open-loop phase: give init_from=<record or folder>")
    if cfg.init_from and not (cfg.rollout.steps or cfg.refine.steps or cfg.minutes or cfg.latents_to):
        raise ConfigError("init_from trains the open-loop phase or the arm refiner: give it rollout.steps > 0 "
                          "(or minutes=) or refine.steps > 0")
    if cfg.latents_to and cfg.latents_from:
        raise ConfigError("latents_to writes a pack here, latents_from trains from one there: give one of them")
    if cfg.minutes is not None and not cfg.minutes > 0:
        raise ConfigError(f"minutes must be > 0 or null (rollout.steps as given), got {cfg.minutes}")
    if cfg.fresh_width is not None and not (isinstance(cfg.fresh_width, int) and cfg.fresh_width >= 8):
        raise ConfigError(f"fresh_width must be an integer >= 8 or null, got {cfg.fresh_width!r}")
    if cfg.camera not in cfg.task.cameras:
        raise ConfigError(f"camera {cfg.camera!r} is not one of the task's cameras {list(cfg.task.cameras)}")
    if not 0.0 <= cfg.flow.ema < 1.0:
        raise ConfigError(f"flow.ema must be in [0, 1), got {cfg.flow.ema}")


def run(cfg: DictConfig) -> dict:
    packed = bool(cfg.latents_from)  # a GPU host: the pack is the data, and there is no simulator
    manifest = start(cfg, validate)
    deadline = time.monotonic() + 60 * cfg.minutes if cfg.minutes else None  # this sitting's wall clock
    contract = task_contract(cfg, registry=not packed)
    device = pick_device(cfg.device)
    config = {k: v for k, v in resolved(cfg).items() if not (k in LATER_DEFAULTS and v == LATER_DEFAULTS[k])}
    tags = {"task": contract.name, "scale": cfg.scale.name, "data": "expert" if cfg.expert_only else "expert+policy"}
    with StageRun(manifest, "train_worldsim", tags, config) as stage:
        base = (resolve_checkpoint(stage, cfg.init_from, "train_worldsim", contract.name, cfg.scale.name)
                if cfg.init_from else None)
        base_model, base_meta = load_checkpoint(base, "worldsim", contract) if base else (None, None)
        paths = [] if packed else collected_episodes(manifest, stage, contract.name, cfg.scale.name, cfg.expert_only,
                                                     cfg.policy_collections)
        pack = read_latent_pack(cfg.latents_from, base).every(cfg.latents_every) if packed else None
        pack_file = None
        if packed:  # by content: another pack is another training, the same one a resume
            contract.check(pack.task, f"latent pack {cfg.latents_from}")
            pack_file = manifest.artefact(cfg.latents_from, kind="latent_pack")
            stage.record.input_files.append(pack_file)
        if (done := stage.finished_before()) is not None:
            return done.metrics
        if packed:
            episodes, held_eps, held = pack.episodes, [], list(base_meta["held_out"])
        else:
            train, held_paths, episodes, held_eps = load_split(paths, cfg.holdout_every, cfg.camera,
                                                               base_meta["held_out"] if base else None)
            held = [episode_key(p) for p in held_paths]
        if cfg.latents_to:
            return pack_latents(stage, cfg, base_model, base, base_meta, episodes, [episode_key(p) for p in train], contract)
        # named by the split too, so that a work dir and the split its weights were trained on cannot disagree
        key = {**config, "held_out": held, **({"latents_from": pack_file.sha256} if packed else {})}
        work = work_dir(cfg.experiment_dir, "train_worldsim", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        if base:  # its camera models and kinematics are part of what it learned
            cameras = {int(t): PinholeCamera.from_dict(c) for t, c in base_meta["cameras"].items()}
            arms = {int(t): SerialArm.from_dict(a) for t, a in (base_meta.get("arms") or {}).items()}
            kinematics = NextStateModel(**base_meta["kinematics"])
        else:
            cameras, arms = task_scenes(contract, cfg.camera, sorted({ep.meta.task_id for ep in episodes + held_eps}),
                                        scenes_file(cfg.experiment_dir))
            kinematics = NextStateModel.fit(episodes)
            log.info("kinematics fitted on %d episodes: %s", len(episodes), kinematics)

        model_cfg = read_config(base)["model"] if base else OmegaConf.to_container(cfg.worldsim, resolve=True)
        start_model = base_model
        if cfg.fresh_width:  # a new flow network on the model's autoencoder: its open-loop steps start from zero,
            # conditioned on the maps this run's config asks for (the arm's links or not)
            model_cfg = {**model_cfg, "arm_map": bool(cfg.worldsim.arm_map)}
            model_cfg, start_model = fresh_velocity(base_model, model_cfg, cfg.fresh_width, cfg.seed)
        if set(arms) != set(cameras) and (model_cfg.get("arm_map") or not packed):  # fidelity scores the arm's region
            arms = scene_arms(cfg, contract, pack, cameras)
        if cfg.refine.steps:  # an arm refiner after the decoder, everything else the starting model's
            model_cfg, start_model = with_refiner(start_model, model_cfg, cfg.refine.width, cfg.seed)
        model = (copy.deepcopy(start_model) if base else instantiate(model_cfg, _convert_="all")).to(device)
        ema = copy.deepcopy(model).requires_grad_(False)
        optimizers = {"ae": torch.optim.AdamW(model.autoencoder.parameters(), lr=cfg.ae.lr),
                      "flow": torch.optim.AdamW(model.velocity.parameters(), lr=cfg.flow.lr),
                      **({"refine": torch.optim.AdamW(model.refiner.parameters(), lr=cfg.refine.lr)}
                         if cfg.refine.steps else {})}
        chunks_of = ((lambda ahead: pack.chunks(model, ahead)) if packed else  # noqa: E731
                     (lambda ahead: episode_chunks(model, episodes, device, fresh=False, chunks_ahead=ahead)))
        if cfg.minutes:  # planned from timed steps on copies, so the run itself starts from the untouched model
            cfg.rollout.steps = planned_total(work, cfg.minutes, lambda s: _time_rollout(model, ema, chunks_of, cameras, arms,
                                                                                        cfg, device, s))
        prior = 0 if cfg.fresh_width or not base else int(base_meta.get("rollout_steps") or 0)
        meta = {"kind": "worldsim", **contract.meta(), "camera": cfg.camera, "kinematics": kinematics.to_dict(),
                "cameras": {str(t): c.to_dict() for t, c in cameras.items()},
                **({"arms": {str(t): a.to_dict() for t, a in arms.items()}} if arms else {}), "episodes": len(episodes),
                "expert_only": bool(cfg.expert_only), "policy_collections": cfg.policy_collections, "held_out": held,
                **({"demo_share": float(cfg.demo_share)} if cfg.get("demo_share") is not None else {}),
                "rollout_steps": prior + int(cfg.rollout.steps),
                **({"refine_steps": int((base_meta or {}).get("refine_steps") or 0) + int(cfg.refine.steps)}
                   if cfg.refine.steps or (base_meta or {}).get("refine_steps") else {}),
                **({"init_from_step": None if cfg.fresh_width else base_meta.get("step")} if base else {}),
                **({"trained_from": {"latent_pack": key["latents_from"][:12], "every": cfg.latents_every,
                                     "fresh_width": cfg.fresh_width}} if packed else {})}
        trainer = Trainer(work, model, optimizers, model_config=model_cfg, meta=meta, desc="train_worldsim",
                          log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                          extra_state=lambda: {"ema": ema.state_dict()},
                          tracker=make_tracker(cfg.get("logger"), work, "train_worldsim", contract.name, config),
                          **trainer_options(cfg, *BATCHES))
        if "ema" in trainer.extra:
            ema.load_state_dict(trainer.extra["ema"])
        frames_of = lambda: torch.cat([torch.from_numpy(ep.images[cfg.camera]) for ep in episodes])  # noqa: E731
        phases = [] if base else [ae_phase(model, optimizers["ae"], frames_of, cfg, device),
                                  flow_phase(model, ema, optimizers["flow"], episodes, cameras, cfg, device, arms)]
        if cfg.rollout.steps:
            phases.append(rollout_phase(model, ema, optimizers["flow"], chunks_of, cameras, cfg, device, arms))
        if cfg.refine.steps:  # after the open-loop phase: the refiner learns to redraw what that flow model imagines
            phases.append(refine_phase(model, ema, optimizers["refine"], lambda ahead: episode_chunks(
                model, episodes, device, fresh=False, chunks_ahead=ahead, frames=True), cameras, cfg, device, arms))
        log.info("training on %d episodes (%d held out): %s on %s; work dir %s", len(episodes), len(held),
                 " + ".join(f"{p.steps} {p.name}" for p in phases), device, work)
        trainer.fit(phases, after_step=snapshots(work, ema, model_cfg, meta, prior, cfg.rollout.steps, cfg.snapshots),
                    deadline=deadline)
        before = sum(p.steps for p in phases if p.name in ("autoencoder", "flow"))
        opened = min(int(cfg.rollout.steps), max(0, trainer.step - before))  # phase-3 steps this run took
        final = trainer.save_final(work / "worldsim", model=ema, rollout_steps=prior + opened)
        if trainer.stopped_early:
            stage.not_recorded = f"the deadline (minutes={cfg.minutes}) came at step {trainer.step}; the same command goes on"
        report = (evaluate_fidelity(cfg, ema, kinematics, cameras, held_eps, work, baseline=base_model, arms=arms)
                  if held_eps else {})
        trainer.tracker.log({f"{k}_h{h}": v[k] for h, v in report.get("fidelity", {}).items()
                             for k in ("model_psnr", "model_ssim", "copy_psnr", "copy_ssim")}, trainer.step, group="eval")
        trainer.finish(stage, final, f"train_worldsim {contract.name}")  # closes the tracker: after the eval curves
        record_fidelity(stage, work, ema, kinematics, cameras, held_eps, final, cfg, arms)
        stage.metrics.update({"episodes": len(episodes), "held_out": len(held), "steps": trainer.step,
                              "train_wall_s": round(trainer.wall_s, 1), "device": str(device), **report})
        log.info("world simulator saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics


def scene_arms(cfg, contract: TaskContract, pack, cameras: dict) -> dict[int, SerialArm]:
    """Each task's arm for a model whose maps draw it, where the starting model kept none: from the latent
    pack on a GPU host (which has no simulator), else from the simulator."""
    if pack is not None:
        if not pack.arms or set(pack.arms) != set(cameras):
            raise ConfigError(f"{cfg.latents_from} carries no arm for every task: write the pack again with this "
                              "version (`latents_to=`) to train a model that draws the arm")
        return {int(t): SerialArm.from_dict(a) for t, a in pack.arms.items()}
    return task_scenes(contract, cfg.camera, sorted(cameras), scenes_file(cfg.experiment_dir))[1]


def record_fidelity(stage, work, ema, kinematics, cameras, held_eps, final, cfg, arms=None) -> None:
    """The fidelity report, its videos and the held-out replays as the run's outputs; with no held-out
    episode here (a latent pack's run), where to measure it."""
    if not held_eps:
        log.info("no held-out episode on this host (a latent pack): measure the model where the episodes are, "
                 "`python -m analysis.fidelity_settings <experiment> --model %s`", final)
        return
    for name in ("fidelity.json", "fidelity.md"):
        stage.add_output(work / name, kind="report")
    for video in sorted((work / "videos").glob("*.gif")):
        stage.add_output(video, kind="video")
    for replay in write_replays(ema, kinematics, cameras, held_eps[: cfg.fidelity.videos], work / "imagined",
                                {"worldsim": str(final)}, cfg.seed, arms):
        stage.add_output(replay, kind="imagined")


def pack_latents(stage, cfg, model, base: str, base_meta: dict, episodes, keys: list[str], contract) -> dict:
    """`latents_to=`: the model's open-loop training set (its held-out episodes left out) as a latent
    pack; nothing is trained, and nothing recorded (no later stage may take the export for a model)."""
    latents = [encode_episode_frames(model, ep.images[base_meta["camera"]]) for ep in episodes]
    arms = base_meta.get("arms") or {str(t): a.to_dict() for t, a in task_scenes(  # for a model drawing the arm
        contract, base_meta["camera"], sorted({ep.meta.task_id for ep in episodes}),
        scenes_file(cfg.experiment_dir))[1].items()}
    out = write_latent_pack(cfg.latents_to, latents, episodes, keys, base, base_meta["camera"], contract.meta(), arms)
    stage.not_recorded = f"it exported the training set to {out}"
    stage.metrics.update({"latent_pack": str(out), "episodes": len(episodes), "frames": sum(len(z) for z in latents),
                          "pack_mib": round(out.stat().st_size / 2 ** 20, 1)})
    log.info("latent pack %s: %d episodes, %d frames, %.1f MiB (the model's %d held-out episodes left out)", out,
             len(episodes), stage.metrics["frames"], stage.metrics["pack_mib"], len(base_meta["held_out"]))
    return stage.metrics


def _time_rollout(model, ema, chunks_of, cameras, arms, cfg, device, seconds: float) -> int:
    """How many open-loop steps fit in `seconds`, timed on copies of the model and its EMA."""
    probe_model, probe_ema = copy.deepcopy(model), copy.deepcopy(ema)
    probe_opt = torch.optim.AdamW(probe_model.velocity.parameters(), lr=cfg.flow.lr)
    probe = rollout_phase(probe_model, probe_ema, probe_opt, chunks_of, cameras, cfg, device, arms)
    return planned_steps(probe.step, iter(probe.batches(0)), seconds)
