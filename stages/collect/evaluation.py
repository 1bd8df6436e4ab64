"""collect's measurements and its section of the experiment report: the scripted expert's success
on the benchmark's fixed init states (`expert_eval.init_states=N`), a preview GIF of a
collection, and the experiment's data (every collection's episodes and success)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from worldenv_core.contract import TaskContract
from worldenv_core.envs.collection import ExpertEvalJob, evaluate_expert_task, summarise_expert_eval
from worldenv_core.envs.tasks import num_tasks
from worldenv_core.manifest import StageRun
from worldenv_core.parallel import run_jobs
from worldenv_core.report import ReportContext, markdown_table, titled

log = logging.getLogger("worldenv.collect")


def expert_eval(cfg: DictConfig, contract: TaskContract, task_ids: list[int], run_dir: Path,
                stage: StageRun) -> list[dict]:
    task = cfg.task
    n = cfg.expert_eval.init_states
    jobs = [ExpertEvalJob(contract, t, tuple(range(n)), cfg.seed) for t in task_ids]
    rows = [row for rs in run_jobs(evaluate_expert_task, jobs, workers=cfg.workers, launcher=cfg.launcher,
                                   desc=f"expert eval {task.suite}", ray_address=cfg.ray_address, progress=cfg.progress,
                                   unit="task")
            for row in rs]
    table = summarise_expert_eval(rows)
    (run_dir / "expert_eval_episodes.json").write_text(json.dumps(rows, indent=1))
    md = [f"Expert success on {task.suite}, first {n} of the benchmark's 50 init states per task "
          f"(of {num_tasks(task.suite)} tasks), max {task.max_steps} steps\n",
          *markdown_table(["task", "name", "success", "mean steps (successes)"],
                          [[r["task_id"], r["task"], f"{r['successes']}/{r['n']} ({100 * r['success_rate']:.0f}%)",
                            f"{r['mean_steps']:.0f}"] for r in table])]
    (run_dir / "expert_table.md").write_text("\n".join(md) + "\n")
    stage.add_output(run_dir / "expert_table.md", kind="report")
    print("\n".join(md))
    return table


def preview(cfg: DictConfig, stage: StageRun, run_dir: Path) -> None:
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


def section(ctx: ReportContext) -> list[str]:
    """The data the experiment trained on: the newest collection of each source and scale."""
    latest = {}
    for r in ctx.find("collect"):
        if r.files("episodes"):
            latest[(r.tags.get("source"), r.tags.get("scale"))] = r
    rows = []
    for (source, scale), r in sorted(latest.items(), key=lambda kv: tuple(map(str, kv[0]))):
        m = r.metrics.get("collection", {})
        rate = m.get("success_rate")
        rows.append([source, scale, len(r.files("episodes")), m.get("kept_frames", ""),
                     "" if rate is None else f"{100 * rate:.0f} %", f"`{r.id}`"])
    return titled("Data (newest collection of each source)", markdown_table(
        ["source", "scale", "episodes", "frames kept (this run)", "success (policy rollouts)", "record"], rows)
        if rows else [])
