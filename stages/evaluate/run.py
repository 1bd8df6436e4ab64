"""Stage `evaluate`: a policy's success in the real LIBERO simulator, per task and per suite,
from the benchmark's fixed init states, under a chosen termination mode."""

from __future__ import annotations

import logging
from contextlib import ExitStack
from datetime import datetime
from itertools import chain
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from stages.evaluate.cache import JobCache, checkpoint_digest
from stages.evaluate.evaluation import record_mode
from stages.report import write_report
from worldenv_core.envs.collection import PolicyEvalJob, evaluate_policy_task
from worldenv_core.envs.tasks import check_suite, num_tasks, resolve_task_ids, suite_max_steps
from worldenv_core.imagination.view import PARTS as VIEW_PARTS
from worldenv_core.manifest import StageRun, config_hash
from worldenv_core.models.checkpoint import read_config
from worldenv_core.rl.termination import check_eta, reflector_eta
from worldenv_core.parallel import run_jobs
from worldenv_core.stage import (POLICY_SOURCES, ConfigError, positive_int, require_task, resolve_checkpoint,
                                 resolve_policy, resolved, start, task_contract)

log = logging.getLogger("worldenv.evaluate")
MODES = ("oracle", "fixed", "reflector")
TERMINATIONS = (*MODES, "all")
JOB_SIZE = 10  # init states per job: small enough to spread a task over workers


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    if cfg.termination not in TERMINATIONS:
        raise ConfigError(f"termination must be one of {', '.join(TERMINATIONS)}, got {cfg.termination!r}")
    positive_int(cfg, "init_states")
    if cfg.get("policy_label") not in (None, *POLICY_SOURCES):
        raise ConfigError(f"policy_label must be one of {', '.join(POLICY_SOURCES)} (or null), got {cfg.policy_label!r}")
    positive_int(cfg, "videos_per_task", allow_zero=True)
    positive_int(cfg, "first_init_state", allow_zero=True)
    if cfg.first_init_state + cfg.init_states > 50:
        raise ConfigError(f"first_init_state + init_states is at most 50 (the benchmark has 50 init states per task), "
                          f"got {cfg.first_init_state} + {cfg.init_states}")
    if cfg.workers is not None:
        positive_int(cfg, "workers")
    try:
        if cfg.eta is not None:  # null: the reflector's own
            check_eta(cfg.eta)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.eval_suite is not None:
        target_suite(cfg)
    if not cfg.view_parts or set(cfg.view_parts) - set(VIEW_PARTS):
        raise ConfigError(f"view_parts must be some of {list(VIEW_PARTS)}, got {list(cfg.view_parts)}")


def target_suite(cfg: DictConfig) -> tuple[str, int]:
    """The suite evaluated on and its step limit: the task's own, or `eval_suite` (any registered
    suite holding the task's task ids, e.g. a LIBERO-PRO variant of the suite trained on) with its
    derived step limit or `eval_max_steps`."""
    if cfg.eval_suite is None:
        return cfg.task.suite, cfg.task.max_steps
    suite = check_suite(cfg.eval_suite)
    for t in resolve_task_ids(cfg.task.suite, cfg.task.task_ids):
        if t >= num_tasks(suite):
            raise ConfigError(f"eval_suite {suite} has {num_tasks(suite)} tasks, but task {cfg.task.name} evaluates "
                              f"task id {t}: evaluate on a suite with the same tasks")
    return suite, suite_max_steps(suite, cfg.eval_max_steps)


def resolve_reflector(cfg: DictConfig, stage: StageRun) -> str:
    """`reflector_from=`: a checkpoint folder, a train_reflector record id, or null (the latest)."""
    path = resolve_checkpoint(stage, cfg.reflector_from, "train_reflector", cfg.task.name, cfg.scale.name)
    camera = read_config(path)["meta"].get("camera")
    if camera not in cfg.task.cameras:
        raise ConfigError(f"reflector {path} watches camera {camera!r}, which task {cfg.task.name} does not render "
                          f"({list(cfg.task.cameras)})")
    return path


def run(cfg: DictConfig) -> dict:
    """One evaluation; termination=all runs each episode once to the horizon with the reflector
    watching and records oracle, fixed and reflector results (identical to three separate runs,
    as policy and simulator are deterministic) for about the cost of one. Returns the summary of
    the requested mode, or {mode: summary} for all."""
    manifest = start(cfg, validate)
    task = cfg.task
    # Outside Hydra (Python, tests) each evaluation gets its own folder too, as Hydra's run dir does,
    # so a later evaluation never overwrites the files an earlier record points at.
    run_dir = (Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized()
               else manifest.root / "evaluate" / f"{cfg.termination}-{datetime.now():%Y-%m-%d_%H-%M-%S-%f}")
    modes = MODES if cfg.termination == "all" else (cfg.termination,)
    policy_tag = cfg.get("policy_label") or (cfg.policy_from if cfg.policy_from in POLICY_SOURCES else "custom")
    suite, max_steps = target_suite(cfg)
    # Only a cross-suite evaluation carries the tag, so the report keeps it apart from the task's own.
    suite_tag = {"eval_suite": suite} if cfg.eval_suite is not None else {}
    # so is one through a world model's eyes (a diagnostic of imagination, not a benchmark result)
    view_tag = {"view": "+".join(cfg.view_parts)} if cfg.view_through is not None else {}
    # and one of a later init-state range (the report's tables are of the first N; `paired` pools ranges)
    range_tag = {"first_init_state": cfg.first_init_state} if cfg.first_init_state else {}
    summaries = {}
    with ExitStack() as records:  # one manifest record per mode, all timed over the shared rollouts
        stages = {m: records.enter_context(StageRun(manifest, "evaluate", {
            "task": task.name, "scale": cfg.scale.name, "termination": m, "policy": policy_tag, **suite_tag, **view_tag,
            **range_tag},
            resolved(cfg))) for m in modes}
        policy_path = [resolve_policy(cfg, s) for s in stages.values()][0]
        digest = checkpoint_digest(policy_path)  # once for every mode: the weights are read whole
        # one evaluation of these weights with these settings at a time (the same again would redo
        # its work beside it); other policies or settings run side by side, each in its own run dir
        identity = config_hash({"policy": digest, **resolved(cfg)})
        next(iter(stages.values())).lock(manifest.root / ".locks" / f"evaluate-{identity}",
                                         f"evaluate of {policy_path} with these settings")
        reflector_path = ([resolve_reflector(cfg, s) for s in stages.values()][0]
                          if cfg.termination in ("reflector", "all") else None)
        eta = reflector_eta(reflector_path, cfg.eta) if reflector_path else None
        view = ([resolve_checkpoint(s, cfg.view_through, "train_worldsim", task.name, cfg.scale.name)
                 for s in stages.values()][0] if cfg.view_through is not None else None)
        inits = list(range(cfg.first_init_state, cfg.first_init_state + cfg.init_states))
        contract = task_contract(cfg).on_suite(suite, max_steps)
        jobs = [PolicyEvalJob(policy_path=policy_path, contract=contract, task_id=t, init_ids=tuple(inits[i:i + JOB_SIZE]),
                              termination=cfg.termination,
                              video_ids=tuple(inits[:cfg.videos_per_task]), reflector_path=reflector_path,
                              eta=eta, view_through=view,
                              view_parts=tuple(cfg.view_parts))
                for t in resolve_task_ids(task.suite, task.task_ids) for i in range(0, len(inits), JOB_SIZE)]
        cache = JobCache(manifest.root) if cfg.reuse_jobs else None
        finished = [cache.get(j) if cache else None for j in jobs]
        todo = {(j.task_id, j.init_ids): j for j, got in zip(jobs, finished) if got is None}
        reused = sum(len(got["rows"]) for got in finished if got) // len(modes)
        if reused:
            log.info("%d of %d jobs (%d episodes) were evaluated before with these weights and settings: reused from %s",
                     len(jobs) - len(todo), len(jobs), reused, cache.root)
        rows, videos = [], {}
        ran = run_jobs(evaluate_policy_task, list(todo.values()), workers=cfg.workers, launcher=cfg.launcher,
                       desc=f"evaluate {task.name} on {suite} ({cfg.termination})", ray_address=cfg.ray_address,
                       progress=cfg.progress, unit="job")
        for fresh, out in chain(((False, got) for got in finished if got), ((True, out) for out in ran)):
            if cache and fresh:  # kept as it finishes: a killed evaluation resumes from here
                first = out["rows"][0]
                cache.put(todo[(first["task_id"], tuple(sorted({r["init_state"] for r in out["rows"]})))], out)
            rows += out["rows"]
            for i, frames in out["videos"].items():
                videos[(out["rows"][0]["task_id"], i)] = frames
        for mode, stage in stages.items():
            out_dir = run_dir / mode if cfg.termination == "all" else run_dir
            summaries[mode] = record_mode(stage, mode, [r for r in rows if r["termination"] == mode], videos,
                                          {"policy": policy_path, "policy_digest": digest,
                                           "init_states": cfg.init_states,
                                           "first_init_state": cfg.first_init_state, "suite": suite,
                                           "max_steps": max_steps}, reflector_path, eta, out_dir)
            # termination=all: the modes share one rollout per episode, counted once (on the first mode);
            # episodes reused from an earlier run of the same weights and settings cost none now
            stage.metrics["real_episodes"] = summaries[mode]["episodes"] - reused if mode == modes[0] else 0
            stage.metrics["reused_episodes"] = reused
            if view is not None:
                stage.metrics["view_through"] = view
    report = write_report(manifest.root, task.name)  # the experiment's report, now with this evaluation
    log.info("experiment report: %s", report)
    return summaries if cfg.termination == "all" else summaries[cfg.termination]
