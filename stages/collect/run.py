"""Stage `collect`: expert demonstrations (and, later, Laplace-perturbed policy rollouts) in the
real LIBERO simulator, written as MCAP episodes and recorded in the manifest."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections import Counter
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from worldenv_core.envs.collection import (
    ExpertEpisodeJob, ExpertEvalJob, PolicyEpisodeJob, collect_expert_episode, collect_policy_episode,
    evaluate_expert_task, summarise_expert_eval,
)
from worldenv_core.data.mcap_io import read_info
from worldenv_core.data.selection import set_aside_damaged
from worldenv_core.envs.tasks import get_task, num_tasks, resolve_task_ids
from worldenv_core.manifest import StageRun, config_hash
from worldenv_core.parallel import run_jobs
from worldenv_core.stage import ConfigError, positive_int, require_task, resolve_policy, resolved, start
log = logging.getLogger("worldenv.collect")
SOURCES = ("expert", "policy", "lerobot")
INIT_MODES = ("sampled", "benchmark")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    if cfg.source not in SOURCES:
        raise ConfigError(f"source must be one of {', '.join(SOURCES)}, got {cfg.source!r}")
    if cfg.source == "policy" and not cfg.noise_scale > 0:
        raise ConfigError(f"noise_scale must be > 0, got {cfg.noise_scale}")
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


def expert_code_hash() -> str:
    import worldenv_core.envs.expert as expert

    h = hashlib.sha256()
    for f in sorted(Path(expert.__file__).parent.glob("*.py")):
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()[:12]


def episode_dir(cfg: DictConfig) -> Path:
    """Episodes of one data-defining configuration live together; a different seed, camera set or
    resolution gets its own folder, so resuming never mixes episodes of two configurations."""
    task = cfg.task
    defining = {"source": cfg.source, "suite": task.suite, "seed": cfg.seed, "init_states": cfg.init_states,
                "max_attempts": cfg.max_attempts, "cameras": list(task.cameras), "image_size": task.image_size,
                "max_steps": task.max_steps}
    if cfg.post_success_steps:  # (only when set, so earlier collections keep their folders)
        defining["post_success_steps"] = cfg.post_success_steps
    if cfg.source == "expert":  # episodes of a changed expert are other episodes: never mix them
        defining["expert_code"] = expert_code_hash()
    if cfg.source == "policy":
        defining.update(policy=str(cfg.policy_from), noise_scale=cfg.noise_scale, stop_on_success=cfg.stop_on_success)
    if cfg.source == "lerobot":
        defining["import"] = [str(cfg.lerobot_import.root), cfg.lerobot_import.repo_id, cfg.lerobot_import.max_episodes]
    return Path(cfg.data_dir) / task.name / f"{cfg.source}-{config_hash(defining)[:8]}"


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task = cfg.task
    task_ids = resolve_task_ids(task.suite, task.task_ids)
    run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else manifest.root
    tags = {"task": task.name, "scale": cfg.scale.name, "source": cfg.source}
    summary: dict = {}
    with StageRun(manifest, "collect", tags, resolved(cfg)) as stage:
        if cfg.expert_eval.init_states > 0:
            summary["expert_eval"] = _expert_eval(cfg, task_ids, run_dir, stage)
        if cfg.source == "lerobot":
            summary["collection"] = _import_lerobot(cfg, stage)
        elif cfg.episodes_per_task > 0:
            summary["collection"] = _collect(cfg, task_ids, stage)
        if stage.record.files("episodes"):
            _preview(cfg, stage, run_dir)
            if cfg.lerobot_export:
                summary["lerobot_export"] = _export_lerobot(cfg, stage)
        stage.metrics.update(summary)
        (run_dir / "collect_summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _collect(cfg: DictConfig, task_ids: list[int], stage: StageRun) -> dict:
    task = cfg.task
    out_dir = episode_dir(cfg)
    common = dict(suite=task.suite, seed=cfg.seed, init_mode=cfg.init_states, cameras=tuple(task.cameras),
                  image_size=task.image_size, max_steps=task.max_steps, fps=float(task.control_freq),
                  post_success_steps=cfg.post_success_steps)
    path = lambda t, k: str(out_dir / f"task{t:02d}" / f"{cfg.source}_{k:04d}.mcap")  # noqa: E731
    if cfg.source == "policy":
        policy_path = resolve_policy(cfg, stage)
        fn, jobs = collect_policy_episode, [
            PolicyEpisodeJob(policy_path=policy_path, task_id=t, index=k, path=path(t, k), chunk=task.chunk,
                             noise_scale=cfg.noise_scale, stop_on_success=cfg.stop_on_success, **common)
            for t in task_ids for k in range(cfg.episodes_per_task)]
    else:
        fn, jobs = collect_expert_episode, [
            ExpertEpisodeJob(task_id=t, index=k, path=path(t, k), max_attempts=cfg.max_attempts, **common)
            for t in task_ids for k in range(cfg.episodes_per_task)]
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
    metrics = {
        "episodes": len(jobs), "kept": status["kept"], "resumed": status["exists"], "failed": status["failed"],
        "attempts_per_kept": sum(r["attempts"] for r in kept) / len(kept) if kept else None,
        "kept_frames": frames, "wall_s": round(wall, 2),
        "kept_frames_per_s": round(frames / wall, 2) if kept else None,
        "render_s": round(sum(r.get("render_s", 0.0) for r in kept), 2),
        "episode_dir": str(out_dir), "recollected_damaged": repaired,
    }
    if cfg.source == "policy":  # over every episode of the collection, resumed ones included
        done = [read_info(r["path"]).meta.success for r in results if r["status"] in ("kept", "exists")]
        metrics["success_rate"] = sum(done) / len(done) if done else None
    log.info("collection: %s", json.dumps(metrics))
    return metrics


def _expert_eval(cfg: DictConfig, task_ids: list[int], run_dir: Path, stage: StageRun) -> list[dict]:
    task = cfg.task
    n = cfg.expert_eval.init_states
    jobs = [ExpertEvalJob(task.suite, t, tuple(range(n)), cfg.seed, task.max_steps) for t in task_ids]
    rows = [row for rs in run_jobs(evaluate_expert_task, jobs, workers=cfg.workers, launcher=cfg.launcher,
                                   desc=f"expert eval {task.suite}", ray_address=cfg.ray_address, progress=cfg.progress,
                                   unit="task")
            for row in rs]
    table = summarise_expert_eval(rows)
    (run_dir / "expert_eval_episodes.json").write_text(json.dumps(rows, indent=1))
    md = [f"Expert success on {task.suite}, first {n} of the benchmark's 50 init states per task "
          f"(of {num_tasks(task.suite)} tasks), max {task.max_steps} steps\n",
          "| task | name | success | mean steps (successes) |", "|---|---|---|---|"]
    md += [f"| {r['task_id']} | {r['task']} | {r['successes']}/{r['n']} ({100 * r['success_rate']:.0f}%) | "
           f"{r['mean_steps']:.0f} |" for r in table]
    (run_dir / "expert_table.md").write_text("\n".join(md) + "\n")
    stage.add_output(run_dir / "expert_table.md", kind="report")
    print("\n".join(md))
    return table


def _export_lerobot(cfg: DictConfig, stage: StageRun) -> str:
    """Export this run's episodes as a LeRobotDataset v3, rebuilt whole (a partial export must
    never look complete) unless the export on disk was made from exactly these episodes: a
    re-run of the pipeline that collected nothing new does not spend minutes exporting again."""
    from worldenv_core.data.lerobot_io import export_lerobot

    root = episode_dir(cfg) / "lerobot"
    repo_id = f"worldenv/{cfg.task.name}_{cfg.source}"
    stamp = {"repo_id": repo_id, "episodes": sorted(a.sha256 for a in stage.record.files("episodes"))}
    made_from = root / "worldenv_export.json"  # written last: present only on a complete export
    if made_from.exists() and json.loads(made_from.read_text()) == stamp:
        log.info("LeRobotDataset v3 export %s is up to date (%d episodes)", root, len(stamp["episodes"]))
    else:
        shutil.rmtree(root, ignore_errors=True)
        paths = stage.manifest.resolve(stage.record, kind="episodes", verify=False)
        export_lerobot(sorted(paths), root, repo_id=repo_id)
        made_from.write_text(json.dumps(stamp))
        log.info("LeRobotDataset v3 export: %s (%d episodes)", root, len(paths))
    stage.add_output(root / "meta" / "info.json", kind="lerobot")
    return str(root)


def _import_lerobot(cfg: DictConfig, stage: StageRun) -> dict:
    """Convert a user's local LeRobotDataset of LIBERO demonstrations into MCAP episodes."""
    from worldenv_core.data.lerobot_io import import_lerobot
    from worldenv_core.data.mcap_io import write_episode

    imp = cfg.lerobot_import
    out_dir = episode_dir(cfg)
    suite = cfg.task.suite
    # Foreign datasets number their tasks their own way: match on the instruction instead.
    by_instruction = {get_task(suite, t).instruction.lower(): get_task(suite, t) for t in range(num_tasks(suite))}
    n = 0
    for i, ep in enumerate(import_lerobot(imp.root, imp.repo_id, suite=suite)):
        if imp.max_episodes is not None and i >= imp.max_episodes:
            break
        spec = by_instruction.get(ep.meta.instruction.strip().lower())
        if spec is None:
            raise ConfigError(f"episode {i} of {imp.root} has instruction {ep.meta.instruction!r}, "
                              f"which is no task of {suite}")
        ep.meta.task_id, ep.meta.task_name, ep.meta.suite = spec.task_id, spec.name, suite
        path = out_dir / f"task{ep.meta.task_id:02d}" / f"import_{i:05d}.mcap"
        if not path.exists():
            write_episode(path, ep)
        stage.add_output(path, kind="episodes")
        n += 1
    if n == 0:
        raise ConfigError(f"the LeRobotDataset at {imp.root} has no episodes")
    log.info("imported %d episodes from %s into %s", n, imp.root, out_dir)
    return {"episodes": n, "episode_dir": str(out_dir)}


def _preview(cfg: DictConfig, stage: StageRun, run_dir: Path) -> None:
    """One GIF with the first episode of every task playing side by side."""
    from worldenv_core.data.mcap_io import read_episode
    from worldenv_core.viz import montage_video

    cam = cfg.task.cameras[0]
    first_per_task: dict[str, Path] = {}
    for p in sorted(stage.manifest.resolve(stage.record, kind="episodes", verify=False)):
        first_per_task.setdefault(p.parent.name, p)
    videos = [read_episode(p, cameras=[cam], load_sim_state=False).images[cam] for p in first_per_task.values()]
    path = montage_video(videos, run_dir / "episodes_preview.gif")
    stage.add_output(path, kind="preview")
    log.info("preview of %d tasks: %s", len(videos), path)
