"""Stage `collect`: expert demonstrations and Laplace-perturbed policy rollouts in the real LIBERO
simulator (or a user's LeRobotDataset), written as MCAP episodes and recorded in the manifest."""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, ListConfig

from stages.collect.episodes import episode_dir, expert_code_hash  # noqa: F401 - part of the stage's API
from stages.collect.evaluation import expert_eval, preview
from stages.collect.lerobot import export_collection, import_dataset
from worldenv_core.data.mcap_io import read_info
from worldenv_core.data.selection import set_aside_damaged
from worldenv_core.envs.collection import (ExpertEpisodeJob, PolicyEpisodeJob, collect_expert_episode,
                                           collect_policy_episode)
from worldenv_core.contract import TaskContract
from worldenv_core.envs.tasks import contract_task_ids, resolve_task_ids
from worldenv_core.files import free_bytes, human_bytes
from worldenv_core.manifest import StageRun
from worldenv_core.parallel import run_jobs
from worldenv_core.stage import ConfigError, positive_int, require_task, resolve_policy, resolved, start, task_contract

log = logging.getLogger("worldenv.collect")
SOURCES = ("expert", "policy", "lerobot")
INIT_MODES = ("sampled", "benchmark")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    if cfg.source not in SOURCES:
        raise ConfigError(f"source must be one of {', '.join(SOURCES)}, got {cfg.source!r}")
    if cfg.source == "policy":
        scales = noise_scales(cfg)
        if not scales or any(isinstance(n, bool) or not isinstance(n, (int, float)) or not n > 0 for n in scales):
            raise ConfigError(f"noise_scale must be a number > 0 or a list of them, got {cfg.noise_scale}")
    if cfg.source == "lerobot" and not cfg.lerobot_import.root:
        raise ConfigError("source=lerobot needs lerobot_import.root=<folder of a local LeRobotDataset>")
    if cfg.source == "lerobot" and not Path(cfg.lerobot_import.root).is_dir():
        raise ConfigError(f"lerobot_import.root {cfg.lerobot_import.root} is not a folder")
    if cfg.init_states not in INIT_MODES:
        raise ConfigError(f"init_states must be one of {', '.join(INIT_MODES)}, got {cfg.init_states!r}")
    positive_int(cfg, "episodes_per_task", allow_zero=True)
    positive_int(cfg, "max_attempts")
    positive_int(cfg, "post_success_steps", allow_zero=True)
    positive_int(cfg, "expert_eval.init_states", allow_zero=True)
    if cfg.expert_eval.init_states > 50:
        raise ConfigError(f"expert_eval.init_states is at most 50 (the benchmark has 50 per task), got {cfg.expert_eval.init_states}")
    if cfg.workers is not None:
        positive_int(cfg, "workers")
    check_collection_size(cfg)


# An episode frame on disk: each camera's PNG (measured 0.33-0.41 of the raw RGB bytes on LIBERO's
# renders at PNG level 1; 0.5 leaves a margin) and the state, action and MuJoCo state records.
PNG_SHARE, STATE_BYTES_PER_FRAME = 0.5, 3000


def collection_bytes(cfg: DictConfig) -> int:
    """At most about how much a collection writes: every episode of every task to the horizon."""
    task = cfg.task
    frame = len(task.cameras) * task.image_size ** 2 * 3 * PNG_SHARE + STATE_BYTES_PER_FRAME
    n_tasks = len(resolve_task_ids(task.suite, task.task_ids))
    return int(cfg.episodes_per_task * n_tasks * (task.max_steps + cfg.post_success_steps + 1) * frame)


def check_collection_size(cfg: DictConfig) -> None:
    """Before anything runs: the collection fits the free space of `data_dir` and the stated bound
    `max_collection_gb` (one line naming both), instead of failing days later on a full disk."""
    if cfg.source not in ("expert", "policy") or not cfg.episodes_per_task:
        return
    need, free = collection_bytes(cfg), free_bytes(cfg.data_dir)
    what = f"{cfg.episodes_per_task} episodes per task would write up to about {human_bytes(need)}"
    if need > cfg.max_collection_gb * 2 ** 30:
        raise ConfigError(f"{what}, over max_collection_gb={cfg.max_collection_gb} ({human_bytes(free)} free in "
                          f"{cfg.data_dir}): collect fewer episodes_per_task or raise max_collection_gb")
    if free is not None and need > free:
        raise ConfigError(f"{what}, more than the {human_bytes(free)} free in data_dir {cfg.data_dir}: free space, "
                          "give another data_dir=<folder> or collect fewer episodes_per_task")


def noise_scales(cfg: DictConfig) -> list:
    """`noise_scale` as a list: one number, or several cycled over each task's episodes."""
    n = cfg.noise_scale
    return list(n) if isinstance(n, (list, tuple, ListConfig)) else [n]


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task = cfg.task
    contract = task_contract(cfg)
    task_ids = contract_task_ids(contract)
    run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else manifest.root
    tags = {"task": task.name, "scale": cfg.scale.name, "source": cfg.source}
    summary: dict = {}
    with StageRun(manifest, "collect", tags, resolved(cfg)) as stage:
        # the policy is an input (used once, here), so a finished collection is known by its weights too
        policy_path = resolve_policy(cfg, stage) if cfg.source == "policy" and cfg.episodes_per_task > 0 else None
        if policy_path and cfg.policy_from == "post_trained":  # its folder names the policy it resolved to, so two
            # refit rounds (each after its own LOOP) never collect into one folder (a resume there would skip episodes)
            where = Path(policy_path).resolve()
            inside = where.is_relative_to(manifest.root)
            cfg.policy_from = where.relative_to(manifest.root).as_posix() if inside else where.name
        # a re-run of `make pipeline`: nothing to redo, if the episodes would go to the same folder (its name
        # also holds the expert's code hash, which the config does not)
        folder = str(episode_dir(cfg)) if cfg.source in ("expert", "policy") and cfg.episodes_per_task > 0 else None
        if folder and (done := stage.finished_before(
                lambda rec: rec.metrics.get("collection", {}).get("episode_dir") == folder)) is not None:
            return {k: v for k, v in done.metrics.items() if k != "real_episodes"}
        if cfg.expert_eval.init_states > 0:
            summary["expert_eval"] = expert_eval(cfg, contract, task_ids, run_dir, stage)
        if cfg.source == "lerobot":
            summary["collection"] = import_dataset(cfg, stage)
        elif cfg.episodes_per_task > 0:
            summary["collection"] = _collect(cfg, contract, task_ids, stage, policy_path)
        if stage.record.files("episodes"):
            preview(cfg, stage, run_dir)
            if cfg.lerobot_export:
                summary["lerobot_export"] = export_collection(cfg, stage)
        stage.metrics.update(summary)
        stage.metrics["real_episodes"] = summary.get("collection", {}).get("real_episodes", 0)
        (run_dir / "collect_summary.json").write_text(json.dumps(summary, indent=2))
    return summary


ROUND = 10  # episodes of a task collected before the next task's: any prefix of a long collection covers every task


def job_order(task_ids: list[int], per_task: int, rounds_of: int = ROUND) -> list[tuple[int, int]]:
    """(task, index) in collection order: rounds of `rounds_of` episodes per task, task after task, so a collection
    stopped part way (a campaign across sessions) holds about as many of every task (and noise scale), and a
    worker still meets one task's scene for ten episodes in a row (cached envs)."""
    return [(t, k) for lo in range(0, per_task, rounds_of) for t in task_ids
            for k in range(lo, min(lo + rounds_of, per_task))]


def _collect(cfg: DictConfig, contract: TaskContract, task_ids: list[int], stage: StageRun,
             policy_path: str | None) -> dict:
    task = cfg.task
    out_dir = episode_dir(cfg)
    common = dict(contract=contract, seed=cfg.seed, init_mode=cfg.init_states,
                  post_success_steps=cfg.post_success_steps)
    path = lambda t, k: str(out_dir / f"task{t:02d}" / f"{cfg.source}_{k:04d}.mcap")  # noqa: E731
    if cfg.source == "policy":
        scales = noise_scales(cfg)
        fn, jobs = collect_policy_episode, [
            PolicyEpisodeJob(policy_path=policy_path, task_id=t, index=k, path=path(t, k),
                             noise_scale=float(scales[k % len(scales)]), stop_on_success=cfg.stop_on_success, **common)
            for t, k in job_order(task_ids, cfg.episodes_per_task)]
    else:
        fn, jobs = collect_expert_episode, [
            ExpertEpisodeJob(task_id=t, index=k, path=path(t, k), max_attempts=cfg.max_attempts, **common)
            for t, k in job_order(task_ids, cfg.episodes_per_task)]
    out_dir.mkdir(parents=True, exist_ok=True)
    stage.lock(out_dir)  # one collection at a time writes this folder
    repaired = set_aside_damaged(stage.manifest, [Path(j.path) for j in jobs])
    log.info("collecting %d %s episodes of %s (%d tasks) into %s", len(jobs), cfg.source, task.suite,
             len(task_ids), out_dir)
    t0 = time.perf_counter()
    results = list(run_jobs(fn, jobs, workers=cfg.workers, launcher=cfg.launcher,
                            desc=f"collect {task.name}", ray_address=cfg.ray_address, progress=cfg.progress))
    wall = time.perf_counter() - t0
    status = Counter(r["status"] for r in results)
    kept = [r for r in results if r["status"] == "kept"]
    for r in results:
        if r["status"] == "failed":
            log.warning("task %d episode %d failed (%s); no episode written", r["task_id"], r["index"],
                        f"{r['attempts']} attempts" if "attempts" in r else r.get("errors"))
    for r in results:
        if r["status"] in ("kept", "exists"):
            stage.add_output(r["path"], kind="episodes")
    frames = sum(r["frames"] for r in kept)
    # Real-simulator episodes this collection cost: every attempt, also those of failed expert
    # demos and of episodes an earlier sitting wrote (their attempts travel in their metadata).
    real = sum(r.get("attempts", 1) for r in results if r["status"] in ("kept", "failed"))
    real += sum(read_info(r["path"]).meta.attempts for r in results if r["status"] == "exists")
    metrics = {
        "episodes": len(jobs), "kept": status["kept"], "resumed": status["exists"], "failed": status["failed"],
        "attempts_per_kept": sum(r["attempts"] for r in kept) / len(kept) if kept else None,
        "kept_frames": frames, "wall_s": round(wall, 2),
        "kept_frames_per_s": round(frames / wall, 2) if kept else None,
        "render_s": round(sum(r.get("render_s", 0.0) for r in kept), 2),
        "episode_dir": str(out_dir), "recollected_damaged": repaired, "real_episodes": real,
    }
    if cfg.source == "policy":  # over every episode of the collection, resumed ones included
        done = [read_info(r["path"]).meta.success for r in results if r["status"] in ("kept", "exists")]
        metrics["success_rate"] = sum(done) / len(done) if done else None
    log.info("collection: %s", json.dumps(metrics))
    return metrics
