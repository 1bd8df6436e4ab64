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

On a GPU host without the episodes, the simulator or the instruction encoder, imagined LOOP runs
from a context pack: `contexts_to=<pack>` here writes the contexts it would train from, and
`contexts_from=<pack> minutes=6` there trains on them (docs/post_training.md#on-a-gpu-host).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from stages.post_train_loop.evaluation import (PairedCheck, imagined_success, real_success, record_imagined,
                                               validation_success, with_gap)
from stages.post_train_loop.sweep import sweep_dir, write_summary
from stages.post_train_loop.es_update import campaign_ledger, context_tasks, es_collector, es_phase, seed_from_ledger
from stages.post_train_loop.training import (Rollouts, check_pack, collector, pack_contexts, paired_guard, rl_phase,
                                             rollouts)
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.distributed import is_main, launched
from worldenv_core.files import write_text_atomic
from worldenv_core.data.selection import POLICY_COLLECTIONS, collected_episodes
from worldenv_core.imagination.context_pack import read_context_pack
from worldenv_core.imagination.env import WHOLE_DEPTH, context_depth
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import load_checkpoint, read_config
from worldenv_core.models.laplace import EXPLORATION
from worldenv_core.rl import es
from worldenv_core.rl.critic import ChunkValue
from worldenv_core.rl.filtered_bc import SuccessBuffer
from worldenv_core.rl.loop import OPTIMIZERS, check_success_range, make_optimizer
from worldenv_core.rl.real_rollouts import retire
from worldenv_core.rl.termination import check_eta
from worldenv_core.stage import (ConfigError, group_size, one_of, positive_int, require_task, resolve_checkpoint,
                                 resolve_policy, resolved, start, task_contract, work_dir)
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device, planned_steps, planned_total

log = logging.getLogger("worldenv.post_train_loop")


# imagined: the method (world simulator + reflector); real: the reference, the real simulator and its oracle
ENVS = ("imagined", "real")
VERDICTS = ("own", "permuted")  # rl.verdicts: the environment's, or the control's shuffle of them
# rl.policy_update: LOOP's PPO step, behaviour cloning of the successes so far, or evolution strategies in weight space
UPDATES = ("ppo", "filtered_bc", "es")
ADVANTAGES = ("rloo", "gae")  # rl.advantages: one per rollout (the paper's RLOO), or per chunk from a critic
CONTEXTS = ("episodes", "placements")  # rl.contexts: collected episodes' starts, or fresh placements (env=real)
# rl settings added after runs were made: at these values a run keeps the work dir it had before them
RL_DEFAULTS = {"mid_episode_frames": 0, "verdicts": "own", "contexts": "episodes", "group_success": None,
               "max_kl": None, "kl_states": 512, "optimizer": "adam", "reset_optimizer": False, "train_scale_head": True,
               "direction_check": False, "noise_scale": 1.0, "guard_contexts": 0, "guard_rollouts": 4,
               "guard_max_hack_rate": 0.5, "policy_update": "ppo", "bc_steps": 200, "bc_minibatch": 32, "bc_augment_shift": 4,
               "placement_pool": None, "advantages": "rloo", "gae_lambda": 0.95, "critic_steps": 500,
               "critic_minibatch": 256, "critic_lr": 1e-3, "critic_hidden": 256, "critic_replay": 0,
               "exploration": "step", "es_pairs": 8, "es_sigma": 0.05, "es_step": 0.05, "es_top": None,
               "es_discount": 1.0, "es_parameters": "mean", "es_ledger_from": None, "task_focus": None,
               "es_min_mixed": 1, "es_return": "success", "context_depth": list(WHOLE_DEPTH)}
# top-level settings added later, kept out of the settings hash and work dir at these values
LATER_DEFAULTS = {"contexts_to": None, "contexts_from": None, "minutes": None, "policy_collections": "latest"}


def validate(cfg: DictConfig) -> None:
    require_task(cfg, registry=not cfg.contexts_from)
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
    one_of(cfg, "policy_collections", POLICY_COLLECTIONS)
    if cfg.eval.imagined_contexts:
        group_size(cfg, "eval.imagined_rollouts")
    group_size(cfg, "rl.n_rollouts")
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
    if cfg.rl.exploration not in EXPLORATION:
        raise ConfigError(f"rl.exploration must be one of {', '.join(EXPLORATION)} (a Laplace draw per step or per "
                          f"chunk), got {cfg.rl.exploration!r}")
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
    try:
        depth = context_depth(cfg.rl)
    except ValueError as e:
        raise ConfigError(f"rl.context_depth: {e}") from None
    if depth != WHOLE_DEPTH and not cfg.rl.mid_episode_frames:
        raise ConfigError(f"rl.context_depth={list(depth)} chooses where mid-episode frames lie: set rl.mid_episode_frames "
                          f"> 0 (episode starts are each episode's first frame)")
    if cfg.rl.contexts == "placements" and (cfg.env != "real" or cfg.rl.mid_episode_frames):
        raise ConfigError("rl.contexts=placements draws fresh scenes in the real simulator: it needs env=real and "
                          "rl.mid_episode_frames=0 (the imagined route starts from recorded frames)")
    if cfg.rl.placement_pool is not None and (cfg.rl.contexts != "placements" or not isinstance(cfg.rl.placement_pool, int)
                                              or cfg.rl.placement_pool < 1):
        raise ConfigError(f"rl.placement_pool is a number of fixed fresh placements (> 0, with rl.contexts=placements) "
                          f"or null, got {cfg.rl.placement_pool!r} with rl.contexts={cfg.rl.contexts}")
    focus = cfg.rl.get("task_focus")
    if focus is not None:
        n_tasks = len(contract_task_ids(task_contract(cfg)))
        if cfg.rl.policy_update != "es" or cfg.rl.placement_pool is not None:
            raise ConfigError("rl.task_focus draws each iteration's contexts from a few tasks in turn: it needs "
                              "rl.policy_update=es, and fresh placements without rl.placement_pool or listed contexts")
        if not isinstance(focus, int) or not 1 <= focus <= n_tasks:
            raise ConfigError(f"rl.task_focus must be null (every task) or an int in 1..{n_tasks} (the tasks trained "
                              f"on), got {focus!r}")
    if cfg.rl.verdicts not in VERDICTS:
        raise ConfigError(f"rl.verdicts must be one of {list(VERDICTS)}, got {cfg.rl.verdicts!r}")
    if cfg.env not in ENVS:
        raise ConfigError(f"env must be one of {list(ENVS)}, got {cfg.env!r}")
    if (cfg.contexts_to or cfg.contexts_from) and cfg.env == "real":
        raise ConfigError("a context pack holds imagined LOOP's contexts: contexts_to / contexts_from need env=imagined")
    if cfg.contexts_to and cfg.contexts_from:
        raise ConfigError("contexts_to writes a pack here, contexts_from trains from one there: give one of them")
    if cfg.minutes is not None and not cfg.minutes > 0:
        raise ConfigError(f"minutes must be > 0 or null (rl.iterations as given), got {cfg.minutes}")
    validate_guard(cfg)
    if cfg.rl.policy_update not in UPDATES:
        raise ConfigError(f"rl.policy_update must be one of {list(UPDATES)}, got {cfg.rl.policy_update!r}")
    if cfg.rl.policy_update == "es":
        validate_es(cfg)
    positive_int(cfg, "rl.bc_steps")
    positive_int(cfg, "rl.bc_minibatch")
    positive_int(cfg, "rl.bc_augment_shift", allow_zero=True)
    if cfg.rl.advantages not in ADVANTAGES:
        raise ConfigError(f"rl.advantages must be one of {list(ADVANTAGES)}, got {cfg.rl.advantages!r}")
    if cfg.rl.advantages == "gae":
        if cfg.rl.policy_update != "ppo":
            raise ConfigError(f"rl.advantages=gae weighs PPO's steps; rl.policy_update={cfg.rl.policy_update} uses none")
        if not 0.0 <= cfg.rl.gae_lambda <= 1.0:
            raise ConfigError(f"rl.gae_lambda must be in [0, 1], got {cfg.rl.gae_lambda}")
        for key in ("rl.critic_steps", "rl.critic_minibatch", "rl.critic_hidden"):
            positive_int(cfg, key)
        positive_int(cfg, "rl.critic_replay", allow_zero=True)
        if not cfg.rl.critic_lr > 0:
            raise ConfigError(f"rl.critic_lr must be > 0, got {cfg.rl.critic_lr}")


def validate_guard(cfg: DictConfig) -> None:
    """`rl.guard_contexts`: the guard replays imagined rollouts where their contexts start for real."""
    positive_int(cfg, "rl.guard_contexts", allow_zero=True)
    if not cfg.rl.guard_contexts:
        return
    if cfg.env == "real" or cfg.contexts_from:
        raise ConfigError("rl.guard_contexts replays imagined rollouts from their contexts' real starts: it needs "
                          "env=imagined and contexts from episodes (a context pack holds no real start)")
    if not isinstance(cfg.rl.guard_rollouts, int) or cfg.rl.guard_rollouts < 1:
        raise ConfigError(f"rl.guard_rollouts must be a positive integer, got {cfg.rl.guard_rollouts}")
    if not 0.0 <= cfg.rl.guard_max_hack_rate <= 1.0:
        raise ConfigError(f"rl.guard_max_hack_rate must be in [0, 1], got {cfg.rl.guard_max_hack_rate}")


def run(cfg: DictConfig) -> dict:
    packed = bool(cfg.contexts_from)  # a GPU host: no episodes, no simulator, no instruction encoder
    manifest = start(cfg, validate)
    deadline = time.monotonic() + 60 * cfg.minutes if cfg.minutes else None  # this sitting's wall clock
    contract, rl = task_contract(cfg, registry=not packed), cfg.rl
    device = pick_device(cfg.device)
    config = {k: v for k, v in resolved(cfg).items() if not (k in LATER_DEFAULTS and v == LATER_DEFAULTS[k])}
    real, sweep = cfg.env == "real", sweep_dir()
    tags = {"task": contract.name, "scale": cfg.scale.name, "eta": None if cfg.eta is None else float(cfg.eta),
            "n_rollouts": int(rl.n_rollouts), "env": cfg.env, **({"sweep": sweep.name} if sweep else {})}
    with StageRun(manifest, "post_train_loop", tags, config) as stage:
        policy_path = resolve_policy(cfg, stage, contract)
        pack = read_context_pack(cfg.contexts_from) if packed else None
        pack_file = None
        if pack is not None:  # by content: another pack is another training, the same one a resume
            check_pack(cfg, contract, pack, f"context pack {cfg.contexts_from}")
            pack_file = manifest.artefact(cfg.contexts_from, kind="context_pack")
            stage.record.input_files.append(pack_file)
        encoder = pack.encoder if packed else _instruction_encoder()
        encode = lambda s: encoder(s).to(device)  # noqa: E731
        policy, pmeta = load_checkpoint(policy_path, "policy", contract, device=str(device))
        fresh = rl.contexts == "placements"  # no collected episode needed: every context a new scene
        episodes = [] if fresh or packed else collected_episodes(manifest, stage, contract.name, cfg.scale.name,
                                                                 cfg.expert_only, cfg.policy_collections)
        worldsim_path, reflector_path = (None, None) if real else (
            resolve_checkpoint(stage, cfg.worldsim_from, "train_worldsim", contract.name, cfg.scale.name),
            resolve_checkpoint(stage, cfg.reflector_from, "train_reflector", contract.name, cfg.scale.name))
        if (done := stage.finished_before()) is not None:
            summarise_sweep(sweep, manifest, contract.name)
            return done.metrics
        src = rollouts(cfg, stage, contract, policy, encode, episodes, worldsim_path, reflector_path, pack, device)
        stage.record.tags["eta"] = src.eta  # the threshold used, also when it is the reflector's own (real: none)
        if cfg.contexts_to:
            return pack_contexts(cfg, stage, contract, src, encoder)
        stage.metrics["contexts"] = "fresh placements" if src.n_contexts is None else src.n_contexts
        key = work_key(config, pack_file and pack_file.sha256)
        work = work_dir(cfg.experiment_dir, "post_train_loop", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        if is_main():  # the resolved config, what analysis reads; in a torchrun launch rank 0 alone writes
            work.mkdir(parents=True, exist_ok=True)
            write_text_atomic(work / "run_config.json", json.dumps(config, indent=1, default=str))
        optimizer = make_optimizer(policy, rl.optimizer, rl.lr_backbone, rl.lr_heads, rl.train_scale_head)
        collect = (es_collector(cfg, contract, src, encode, policy_path, pmeta, work) if rl.policy_update == "es"
                   else collector(cfg, contract, src, encode, policy_path, pmeta, work))
        if cfg.minutes:  # planned from iterations timed on copies, so the run itself starts from the untouched policy
            rl.iterations = planned_total(work, cfg.minutes, lambda s: _time_iterations(policy, collect, src, rl, cfg, s))
        provenance = {"policy": policy_path, "worldsim": worldsim_path, "reflector": reflector_path}
        value = (ChunkValue(-(-int(rl.horizon) // contract.chunk), rl.critic_hidden, rl.critic_lr, rl.critic_steps,
                            rl.critic_minibatch, rl.gae_lambda, rl.critic_replay) if rl.advantages == "gae" else None)
        start_weights = None
        if rl.policy_update == "es" and rl.get("es_ledger_from"):  # a campaign's ledger, on an empty work dir
            start_weights = es.weights_digest(policy)  # what its steps are made on, named in the folder and checked there
            seed_from_ledger(work, rl.es_ledger_from, policy, {"ppo": optimizer}, read_config(policy_path)["model"],
                             loop_meta(pmeta, provenance, src, key.get("contexts_from")), rl, start_weights)
        trainer = Trainer(work, policy, {"ppo": optimizer}, model_config=read_config(policy_path)["model"],
                          meta=loop_meta(pmeta, provenance, src, key.get("contexts_from")), log_every=1, checkpoint_every=1, desc="post_train_loop", progress=cfg.progress,
                          postfix=("mean_reward", "reflector_success_rate", "approx_kl"),
                          tracker=make_tracker(cfg.get("logger"), work, "post_train_loop", contract.name, config),
                          extra_state=(lambda: {"critic": value.state_dict()}) if value else None)
        if value is not None and "critic" in trainer.extra:  # a resumed run: the critic as of its last iteration
            value.load_state_dict(trainer.extra["critic"], device)
        per_context = (f"{2 * rl.es_pairs} weight-space members" if rl.policy_update == "es" else f"{rl.n_rollouts} rollouts")
        log.info("post-training %s for %d iterations in the %s environment: %d contexts x %s each, eta %s, "
                 "on %s; work dir %s", policy_path, rl.iterations, cfg.env, rl.contexts_per_iteration, per_context,
                 "oracle" if real else f"{src.eta:.2f}", device, work)
        evaluate = evaluator(cfg, contract, src, policy, policy_path, encode, trainer, work, packed, provenance)
        buffer = SuccessBuffer(work / "success_buffer") if rl.policy_update == "filtered_bc" else None  # kept: the data
        guard = paired_guard(cfg, contract, src, encode)
        phase = (es_phase(policy, collect, src.n_contexts, rl, cfg.seed, work / "es_ledger", guard,
                          len(contract_task_ids(contract)), context_tasks(cfg, contract, src)) if rl.policy_update == "es" else
                 rl_phase(policy, optimizer, collect, src.n_contexts, rl, cfg.seed, guard, buffer, value))
        with campaign_ledger(work, rl, start_weights) as keep_ledger:
            trainer.fit([phase], evaluate=evaluate, evaluate_every=cfg.eval.every, deadline=deadline,
                        after_save=keep_ledger)
        for journal in (work / "rollout_journal").glob("*"):  # every iteration it kept is checkpointed now
            retire(journal, work / "kept_rollouts" if rl.keep_rollouts else None)
        shutil.rmtree(work / "rollout_journal", ignore_errors=True)
        final = trainer.save_final(work / "policy", iteration=trainer.step)
        if trainer.stopped_early:
            stage.not_recorded = f"the deadline (minutes={cfg.minutes}) came at iteration {trainer.step}; the same command goes on"
        trainer.finish(stage, final, f"post_train_loop {contract.name}", plot="training.png")
        stage.add_output(work / "training.json", kind="report")
        for path in sorted((work / "imagined").glob("iter_*/*.mcap")):  # every sitting's, also before a resume
            stage.add_output(path, kind="imagined")
        stage.metrics.update(run_metrics(cfg, contract, trainer, device))
        log.info("post-trained policy saved to %s; metrics %s", final, json.dumps(stage.metrics))
    summarise_sweep(sweep, manifest, contract.name)
    return stage.metrics


def validate_es(cfg: DictConfig) -> None:
    """rl.policy_update=es: sizes that make a step; in imagination, one process (the members' rollouts are
    one batch through the world model)."""
    from worldenv_core.rl.es import PARAMETER_SETS, RETURNS

    if launched() > 1:
        raise ConfigError(f"rl.policy_update=es runs in one process (its members share one batch), but torchrun "
                          f"launched {launched()}")
    positive_int(cfg, "rl.es_pairs")
    for key in ("es_sigma", "es_step"):
        if not cfg.rl[key] > 0:
            raise ConfigError(f"rl.{key} must be > 0 (a size relative to each weight tensor's RMS), got {cfg.rl[key]}")
    if not 0 < cfg.rl.es_discount <= 1:
        raise ConfigError(f"rl.es_discount must be in (0, 1] (1: the return is the success), got {cfg.rl.es_discount}")
    if cfg.rl.get("es_return", "success") not in RETURNS:
        raise ConfigError(f"rl.es_return must be one of {list(RETURNS)}, got {cfg.rl.es_return!r}")
    if cfg.rl.get("es_return") == "score" and cfg.env == "real":
        raise ConfigError("rl.es_return=score needs env=imagined (the reflector's score); the real route's return is "
                          "the benchmark's success")
    if cfg.rl.es_top is not None and not (isinstance(cfg.rl.es_top, int) and 0 < cfg.rl.es_top <= cfg.rl.es_pairs):
        raise ConfigError(f"rl.es_top must be null (every pair) or an int in 1..rl.es_pairs, got {cfg.rl.es_top!r}")
    positive_int(cfg, "rl.es_min_mixed", allow_zero=True)
    if cfg.rl.es_parameters not in PARAMETER_SETS:
        raise ConfigError(f"rl.es_parameters must be one of {list(PARAMETER_SETS)}, got {cfg.rl.es_parameters!r}")


def episodes_per_iteration(rl) -> int:
    """Real episodes one iteration trains on: N rollouts per context, or (ES) both members of each pair per context."""
    return rl.contexts_per_iteration * (2 * rl.es_pairs if rl.policy_update == "es" else rl.n_rollouts)


def work_key(config: dict, pack_sha256: str | None) -> dict:
    """What names the work dir (what resume finds): what defines the training and its inputs, not how
    it is evaluated or shown (changing eval.* or progress continues the same run); rl settings added
    later count only away from their defaults, so earlier runs keep their work dirs; a context pack
    by its content."""
    key = {k: v for k, v in config.items() if k not in ("eval", "progress")}
    key["rl"] = {k: v for k, v in key["rl"].items() if not (k in RL_DEFAULTS and v == RL_DEFAULTS[k])
                 and k not in ("keep_rollouts", "es_ledger_from")}  # what is kept, and where a run was seeded from,
    # are not what is trained: a campaign seeded from its ledger keeps its work dir's name
    return {**key, "contexts_from": pack_sha256} if pack_sha256 else key


def loop_meta(pmeta: dict, provenance: dict, src: Rollouts, pack_sha256: str | None) -> dict:
    """The post-trained policy's meta: its starting policy's, what it was post-trained from and in."""
    meta = {**pmeta, "post_trained_from": provenance["policy"], "worldsim": provenance["worldsim"],
            "reflector": provenance["reflector"]}
    if pack_sha256:
        meta["trained_from"] = {"context_pack": pack_sha256[:12], "contexts": src.n_contexts, "eta": src.eta}
    return meta


def _instruction_encoder():
    from worldenv_core.models.text import InstructionEncoder  # here: a context pack's run needs none

    return InstructionEncoder()


def _time_iterations(policy, collect, src: Rollouts, rl, cfg: DictConfig, seconds: float) -> int:
    """How many iterations fit in `seconds`, timed on copies of the policy and its optimizer."""
    import copy

    probe_policy = copy.deepcopy(policy)
    probe_opt = make_optimizer(probe_policy, rl.optimizer, rl.lr_backbone, rl.lr_heads, rl.train_scale_head)
    probe_rl = copy.deepcopy(rl)
    probe_rl.iterations = 4
    probe = (es_phase(probe_policy, collect, src.n_contexts, probe_rl, cfg.seed) if rl.policy_update == "es" else
             rl_phase(probe_policy, probe_opt, collect, src.n_contexts, probe_rl, cfg.seed, buffer=SuccessBuffer(None)))
    return planned_steps(probe.step, iter(probe.batches(0)), seconds, probe=3, warm=1)


def evaluator(cfg: DictConfig, contract, src: Rollouts, policy, policy_path: str, encode, trainer, work: Path,
              packed: bool, provenance: dict):
    """`evaluate(done, checkpoint)` for the Trainer: imagined success on fixed contexts, real success and
    the validation set (where the simulator is: not from a context pack), a few recorded imagined rollouts."""
    real, sim = cfg.env == "real", not packed

    def evaluate(done: int, checkpoint: Path | None) -> dict:
        values, policy_at = {}, str(checkpoint or policy_path)
        if cfg.eval.imagined_contexts and not real:
            paired = (PairedCheck(contract, src.starts, cfg.eval.paired_contexts, cfg.eval.workers, cfg.progress)
                      if cfg.eval.every and sim else None)  # beside every real evaluation
            values.update(imagined_success(policy, src.env, src.contexts, cfg.eval.imagined_contexts,
                                           cfg.eval.imagined_rollouts, encode, cfg.seed, paired))
        if cfg.eval.every and cfg.eval.init_states and sim:
            values["real_success"] = real_success(policy_at, contract, cfg.eval.init_states, cfg.eval.workers, cfg.progress)
        if checkpoint is not None and cfg.eval.keep_policies:  # the policy at this point, for benchmark runs later
            trainer.save_final(work / "evaluated" / f"iter_{done:04d}", iteration=done)
        if cfg.eval.every and cfg.eval.validation and sim:  # what a recipe is judged by, never the benchmark
            values.update(validation_success(policy_at, contract, cfg.eval.validation, cfg.eval.workers, cfg.progress,
                                             cache=work.parent / "validation_cache" if cfg.eval.get("validation_cache", True)
                                             else None))
        if cfg.eval.record_contexts and not real and sim:
            record_imagined(policy, src.env, src.contexts, cfg.eval.record_contexts, contract, encode, src.camera,
                            work / "imagined" / f"iter_{done:04d}", {**provenance, "iteration": str(done)}, cfg.seed)
        log.info("evaluation at iteration %d: %s", done, json.dumps(with_gap(values)))
        return values
    return evaluate


def run_metrics(cfg: DictConfig, contract, trainer, device) -> dict:
    """The record's metrics: the curves by iteration and every real episode, by use."""
    rl, history = cfg.rl, trainer.history
    by_step = lambda key: {str(h["step"]): h[key] for h in history if key in h}  # noqa: E731
    real_evaluations = len(by_step("real_success"))  # none from a context pack: no task registry needed there
    return {"iterations": trainer.step, "train_wall_s": round(trainer.wall_s, 1), "device": str(device),
            "final_mean_reward": history[-1].get("mean_reward"), "real_success": by_step("real_success"),
            "imagined_reward": by_step("imagined_reward"), "validation_success": by_step("validation_success"),
            "imagined_success": by_step("imagined_success"),
            # evaluation: monitoring only, never a training signal
            "real_episodes": (real_evaluations and real_evaluations * cfg.eval.init_states * len(contract_task_ids(contract)))
            + int(sum(h.get("paired_episodes", 0) + h.get("guard_episodes", 0) + h.get("validation_episodes", 0)
                      for h in history)),  # a count (the history keeps the guard's as a float among its stats)
            "guard_hack_rate": by_step("guard_hack_rate"), "rolled_back": sum(h.get("rolled_back", 0) for h in history),
            "paired_hack_rate": by_step("paired_hack_rate"), "paired_imagined_mixed": by_step("paired_imagined_mixed"),
            "paired_real_mixed": by_step("paired_real_mixed"),
            # the reference trains on real episodes: what the imagined route is compared at
            "train_real_episodes": trainer.step * episodes_per_iteration(rl) if cfg.env == "real" else 0,
            "kept_groups": float(np.mean([h["kept_groups"] for h in history if "kept_groups" in h] or [float("nan")]))}


def summarise_sweep(sweep, manifest, task: str) -> None:
    """The sweep's summary so far, beside its runs (the report draws it again)."""
    if sweep:
        log.info("sweep summary: %s", write_summary(sweep, manifest.find("post_train_loop", task=task, sweep=sweep.name)))
