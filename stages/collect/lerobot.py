"""collect's LeRobotDataset v3 bridge: import a user's local LIBERO dataset as MCAP episodes
(`source=lerobot`), and export a collection as a LeRobotDataset (`lerobot_export=true`)."""

from __future__ import annotations

import json
import logging
import shutil

from omegaconf import DictConfig

from stages.collect.episodes import episode_dir
from worldenv_core.envs.tasks import get_task, num_tasks
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import StageRun

log = logging.getLogger("worldenv.collect")


def export_collection(cfg: DictConfig, stage: StageRun) -> str:
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


def import_dataset(cfg: DictConfig, stage: StageRun) -> dict:
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
