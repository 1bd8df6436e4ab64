"""Stage `post_train_loop`: LOOP (RLOO + PPO) post-training inside the world model (paper
sec. 4.3, Algorithm 1).

Every iteration freezes a behaviour copy of the policy, samples `contexts_per_iteration`
contexts (first frame, proprio and instruction of collected episodes: fresh seeded placements,
never the benchmark init states that evaluation uses), runs N imagined rollouts per context
with Laplace-sampled actions until the reflector's R > eta or the horizon, computes RLOO
advantages from R at t_end, and takes `ppo_epochs` passes of the clipped objective. Every
`eval.every` iterations (and before the first) the policy is measured in the real simulator.

`env=real` is the reference: the same LOOP from the same contexts with the real simulator as the
environment and its success oracle as the reward (no world model, no reflector); every rollout
is a real episode, counted in the record.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from stages.post_train_loop.evaluation import (PairedCheck, imagined_success, real_success, record_imagined,
                                               validation_success, with_gap)
from stages.post_train_loop.sweep import sweep_dir, write_summary
from stages.post_train_loop.training import (contexts_from_episodes, imagined_collector, placements, real_collector,
                                             real_starts, rl_phase)
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.distributed import is_main, launched
from worldenv_core.files import write_text_atomic
from worldenv_core.envs.replay import RealStart, unreplayable
from worldenv_core.imagination.env import build_imagined_env
from worldenv_core.data.selection import collected_episodes
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import load_checkpoint, read_config
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.rl.loop import OPTIMIZERS, check_success_range, make_optimizer
from worldenv_core.rl.termination import check_eta, reflector_eta
from worldenv_core.stage import (ConfigError, positive_int, require_task, resolve_checkpoint, resolve_policy, resolved,
                                 start, task_contract, work_dir)
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device

log = logging.getLogger("worldenv.post_train_loop")


# imagined: the method (world simulator + reflector); real: the reference, the real simulator and its oracle
ENVS = ("imagined", "real")
VERDICTS = ("own", "permuted")  # rl.verdicts: the environment's, or the control's shuffle of them
CONTEXTS = ("episodes", "placements")  # rl.contexts: collected episodes' starts, or fresh placements (env=real)
# rl settings added after runs were made: at these values a run keeps the work dir it had before them
RL_DEFAULTS = {"mid_episode_frames": 0, "verdicts": "own", "contexts": "episodes", "group_success": None,
               "max_kl": None, "kl_states": 512, "optimizer": "adam", "reset_optimizer": False, "train_scale_head": True,
               "direction_check": False, "noise_scale": 1.0}


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    if launched() > 1 and cfg.env == "real":  # real rollouts fan out over worker processes instead
        raise ConfigError(f"env=real runs in one process (its rollouts use workers=), but torchrun launched "
                          f"{launched()}")
    if cfg.rl.contexts_per_iteration % launched():
        raise ConfigError(f"rl.contexts_per_iteration={cfg.rl.contexts_per_iteration} does not split over the "
                          f"{launched()} ranks torchrun launched: use a multiple of {launched()}")
    for key in ("rl.iterations", "rl.contexts_per_iteration", "rl.ppo_epochs", "rl.minibatch", "rl.horizon"):
        positive_int(cfg, key)
    positive_int(cfg, "eval.every", allow_zero=True)
    positive_int(cfg, "eval.init_states", allow_zero=True)
    positive_int(cfg, "eval.validation", allow_zero=True)
    positive_int(cfg, "rl.kl_states")
    positive_int(cfg, "eval.imagined_contexts", allow_zero=True)
    positive_int(cfg, "eval.record_contexts", allow_zero=True)
    positive_int(cfg, "eval.paired_contexts", allow_zero=True)
    positive_int(cfg, "rl.mid_episode_frames", allow_zero=True)
    if cfg.eval.imagined_contexts and cfg.eval.imagined_rollouts < 2:
        raise ConfigError(f"eval.imagined_rollouts must be at least 2, got {cfg.eval.imagined_rollouts}")
    if not isinstance(cfg.rl.n_rollouts, int) or cfg.rl.n_rollouts < 2:
        raise ConfigError(f"rl.n_rollouts must be at least 2 (the RLOO baseline averages the other N - 1), "
                          f"got {cfg.rl.n_rollouts}")
    try:
        if cfg.eta is not None:  # null: the reflector's own
            check_eta(cfg.eta)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if not cfg.rl.epsilon > 0:
        raise ConfigError(f"rl.epsilon (the PPO clip) must be > 0, got {cfg.rl.epsilon}")
    if cfg.rl.target_kl is not None and not cfg.rl.target_kl > 0:
        raise ConfigError(f"rl.target_kl must be > 0 or null (no limit), got {cfg.rl.target_kl}")
    if min(cfg.rl.lr_backbone, cfg.rl.lr_heads) < 0 or not max(cfg.rl.lr_backbone, cfg.rl.lr_heads) > 0:
        raise ConfigError(f"rl.lr_backbone and rl.lr_heads must be >= 0 (0: that group is not trained) and one of "
                          f"them > 0, got {cfg.rl.lr_backbone} and {cfg.rl.lr_heads}")
    if cfg.rl.max_kl is not None and not cfg.rl.max_kl > 0:
        raise ConfigError(f"rl.max_kl (the trust region) must be > 0 or null (none), got {cfg.rl.max_kl}")
    if not cfg.rl.noise_scale > 0:
        raise ConfigError(f"rl.noise_scale (the rollouts' sampling temperature) must be > 0, got {cfg.rl.noise_scale}")
    if cfg.rl.optimizer not in OPTIMIZERS:
        raise ConfigError(f"rl.optimizer must be one of {list(OPTIMIZERS)}, got {cfg.rl.optimizer!r}")
    try:
        check_success_range(cfg.rl.group_success)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"rl.group_success: {e}") from None
    if cfg.rl.contexts not in CONTEXTS:
        raise ConfigError(f"rl.contexts must be one of {list(CONTEXTS)}, got {cfg.rl.contexts!r}")
    if cfg.rl.contexts == "placements" and (cfg.env != "real" or cfg.rl.mid_episode_frames):
        raise ConfigError("rl.contexts=placements draws fresh scenes in the real simulator: it needs env=real and "
                          "rl.mid_episode_frames=0 (the imagined route starts from recorded frames)")
    if cfg.rl.verdicts not in VERDICTS:
        raise ConfigError(f"rl.verdicts must be one of {list(VERDICTS)}, got {cfg.rl.verdicts!r}")
    if cfg.env not in ENVS:
        raise ConfigError(f"env must be one of {list(ENVS)}, got {cfg.env!r}")


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    contract, rl = task_contract(cfg), cfg.rl
    device = pick_device(cfg.device)
    config = resolved(cfg)
    real, sweep = cfg.env == "real", sweep_dir()
    tags = {"task": contract.name, "scale": cfg.scale.name, "eta": None if cfg.eta is None else float(cfg.eta),
            "n_rollouts": int(rl.n_rollouts), "env": cfg.env, **({"sweep": sweep.name} if sweep else {})}
    with StageRun(manifest, "post_train_loop", tags, config) as stage:
        policy_path = resolve_policy(cfg, stage)
        encoder = InstructionEncoder()
        encode = lambda s: encoder(s).to(device)  # noqa: E731
        policy, pmeta = load_checkpoint(policy_path, "policy", contract, device=str(device))
        task_ids = set(contract_task_ids(contract))  # task.task_ids=[...] trains on those tasks' contexts only
        fresh = rl.contexts == "placements"  # no collected episode needed: every context a new scene
        episodes = [] if fresh else collected_episodes(manifest, stage, contract.name, cfg.scale.name, cfg.expert_only)
        if not real:
            worldsim_path = resolve_checkpoint(stage, cfg.worldsim_from, "train_worldsim", contract.name, cfg.scale.name)
            reflector_path = resolve_checkpoint(stage, cfg.reflector_from, "train_reflector", contract.name, cfg.scale.name)
        if (done := stage.finished_before()) is not None:
            summarise_sweep(sweep, manifest, contract.name)
            return done.metrics

        def chosen(starts: list[RealStart]) -> list[int]:
            """The starts of the tasks trained on (`task.task_ids`), less the mid-episode ones whose
            recorded prefix does not replay (no real rollout or paired replay could start there),
            dropped and named before any rollout."""
            mine = [i for i, st in enumerate(starts) if st.task_id in task_ids]
            errors = unreplayable(contract, [starts[i] for i in mine], workers=cfg.eval.workers,
                                  progress=cfg.progress) if rl.mid_episode_frames else {}
            for error in errors.values():
                log.warning("context dropped: %s", error)
            stage.metrics["dropped_contexts"] = len(errors)
            return [i for i in mine if starts[i].key not in errors]
        if real:  # the reference: no world model, no reflector; the oracle decides
            worldsim_path = reflector_path = env = None
            camera, eta = contract.cameras[0], None
            stage.record.tags["eta"] = None
            if policy.cameras != [camera]:
                raise ConfigError(f"the policy looks at {policy.cameras}; env=real renders only {camera!r} for it")
            starts, instructions = real_starts(episodes, rl.mid_episode_frames)
            keep = chosen(starts)
            starts, instructions = [starts[i] for i in keep], [instructions[i] for i in keep]
            n_contexts = None if fresh else len(starts)
        else:
            eta = reflector_eta(reflector_path, cfg.eta)
            stage.record.tags["eta"] = eta  # the threshold used, also when it is the reflector's own
            env, camera = build_imagined_env(worldsim_path, reflector_path, eta, encode, rl.horizon, rl.sampling_steps,
                                             device, contract, rl.sampler_noise)
            if policy.cameras != [camera]:
                raise ConfigError(f"the policy looks at {policy.cameras}, but the world simulator imagines only {camera!r}")
            contexts, starts = contexts_from_episodes(episodes, camera, rl.mid_episode_frames)
            keep = chosen(starts)
            contexts, starts = [contexts[i] for i in keep], [starts[i] for i in keep]
            n_contexts = len(contexts)
        if n_contexts == 0:
            raise ConfigError(f"no collected episode of task(s) {sorted(task_ids)} to start rollouts from")
        stage.metrics["contexts"] = "fresh placements" if fresh else n_contexts
        # The work dir (what resume finds) is named by what defines the training and by its inputs,
        # not by how it is evaluated or shown: changing eval.* or progress continues the same run.
        key = {k: v for k, v in config.items() if k not in ("eval", "progress")}
        # added later: at their defaults (first frames only, the environment's own verdicts) they keep the
        # work dirs of earlier runs
        key["rl"] = {k: v for k, v in key["rl"].items() if not (k in RL_DEFAULTS and v == RL_DEFAULTS[k])}
        work = work_dir(cfg.experiment_dir, "post_train_loop", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        if is_main():  # the resolved config, what analysis reads; in a torchrun launch rank 0 alone writes
            work.mkdir(parents=True, exist_ok=True)
            write_text_atomic(work / "run_config.json", json.dumps(config, indent=1, default=str))
        optimizer = make_optimizer(policy, rl.optimizer, rl.lr_backbone, rl.lr_heads, rl.train_scale_head)
        provenance = {"policy": policy_path, "worldsim": worldsim_path, "reflector": reflector_path}
        trainer = Trainer(work, policy, {"ppo": optimizer}, model_config=read_config(policy_path)["model"],
                          meta={**pmeta, "post_trained_from": policy_path, "worldsim": worldsim_path,
                                "reflector": reflector_path},
                          log_every=1, checkpoint_every=1, desc="post_train_loop", progress=cfg.progress,
                          postfix=("mean_reward", "reflector_success_rate", "approx_kl"),
                          tracker=make_tracker(cfg.get("logger"), work, "post_train_loop", contract.name, config))
        log.info("post-training %s for %d iterations in the %s environment: %d contexts x %d rollouts each, eta %s, "
                 "on %s; work dir %s", policy_path, rl.iterations, cfg.env, rl.contexts_per_iteration, rl.n_rollouts,
                 "oracle" if real else f"{eta:.2f}", device, work)

        def evaluate(done: int, checkpoint: Path | None) -> dict:
            """Imagined success on fixed contexts, real success, a few recorded imagined rollouts."""
            values = {}
            if cfg.eval.imagined_contexts and not real:
                paired = (PairedCheck(contract, starts, cfg.eval.paired_contexts, cfg.eval.workers, cfg.progress)
                          if cfg.eval.every else None)  # beside every real evaluation
                values.update(imagined_success(policy, env, contexts, cfg.eval.imagined_contexts,
                                               cfg.eval.imagined_rollouts, encode, cfg.seed, paired))
            if cfg.eval.every and cfg.eval.init_states:
                values["real_success"] = real_success(str(checkpoint or policy_path), contract, cfg.eval.init_states,
                                                      cfg.eval.workers, cfg.progress)
            if checkpoint is not None and cfg.eval.keep_policies:  # the policy at this point, for benchmark runs later
                trainer.save_final(work / "evaluated" / f"iter_{done:04d}", iteration=done)
            if cfg.eval.every and cfg.eval.validation:  # what a recipe is judged by, never the benchmark
                values.update(validation_success(str(checkpoint or policy_path), contract, cfg.eval.validation,
                                                 cfg.eval.workers, cfg.progress))
            if cfg.eval.record_contexts and not real:
                record_imagined(policy, env, contexts, cfg.eval.record_contexts, contract, encode, camera,
                                work / "imagined" / f"iter_{done:04d}", {**provenance, "iteration": str(done)}, cfg.seed)
            log.info("evaluation at iteration %d: %s", done, json.dumps(with_gap(values)))
            return values

        collect = (real_collector(contract, placements(contract) if fresh else starts, instructions, rl.n_rollouts,
                                  encode, rl.horizon,
                                  read_config(policy_path)["model"], pmeta, work, cfg.eval.workers, cfg.progress,
                                  rl.noise_scale)
                   if real else imagined_collector(env, contexts, rl.n_rollouts, encode, rl.noise_scale))
        trainer.fit([rl_phase(policy, optimizer, collect, n_contexts, rl, cfg.seed)], evaluate=evaluate,
                    evaluate_every=cfg.eval.every)
        final = trainer.save_final(work / "policy", iteration=rl.iterations)
        trainer.finish(stage, final, f"post_train_loop {contract.name}", plot="training.png")
        stage.add_output(work / "training.json", kind="report")
        for path in sorted((work / "imagined").glob("iter_*/*.mcap")):  # every sitting's, also before a resume
            stage.add_output(path, kind="imagined")
        history = trainer.history
        by_step = lambda key: {str(h["step"]): h[key] for h in history if key in h}  # noqa: E731
        stage.metrics.update({"iterations": rl.iterations, "train_wall_s": round(trainer.wall_s, 1),
                              "device": str(device), "final_mean_reward": history[-1].get("mean_reward"),
                              "real_success": by_step("real_success"), "imagined_reward": by_step("imagined_reward"),
                              "validation_success": by_step("validation_success"),
                              "imagined_success": by_step("imagined_success"),
                              # evaluation: monitoring only, never a training signal
                              "real_episodes": len(by_step("real_success")) * cfg.eval.init_states
                              * len(contract_task_ids(contract)) + sum(h.get("paired_episodes", 0) for h in history)
                              + sum(h.get("validation_episodes", 0) for h in history),
                              "paired_hack_rate": by_step("paired_hack_rate"),
                              "paired_imagined_mixed": by_step("paired_imagined_mixed"),
                              "paired_real_mixed": by_step("paired_real_mixed"),
                              # the reference trains on real episodes: what the imagined route is compared at
                              "train_real_episodes": rl.iterations * rl.contexts_per_iteration * rl.n_rollouts if real else 0,
                              "kept_groups": float(np.mean([h["kept_groups"] for h in history if "kept_groups" in h]
                                                           or [float("nan")]))})
        log.info("post-trained policy saved to %s; metrics %s", final, json.dumps(stage.metrics))
    summarise_sweep(sweep, manifest, contract.name)
    return stage.metrics


def summarise_sweep(sweep, manifest, task: str) -> None:
    """The sweep's summary so far, beside its runs (the report draws it again)."""
    if sweep:
        log.info("sweep summary: %s", write_summary(sweep, manifest.find("post_train_loop", task=task, sweep=sweep.name)))
