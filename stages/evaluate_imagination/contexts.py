"""The contexts paired replay starts from, none of which the world model or the reflector trained
on: the first benchmark init states of each task (collections start from fresh placements), and
frames in the middle of held-out episodes (held out by both the world model and the reflector).
With `contexts.source=training`, frames of training episodes instead: pairs to train a reflector
on (imagined video labelled with the real outcome of the same actions), not a measurement."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.contract import TaskContract
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.data.selection import MissingEpisodesError, collected_episodes, episode_key
from worldenv_core.envs.recording import cached_env
from worldenv_core.envs.replay import RealStart, StartJob, restore, unreplayable
from worldenv_core.envs.replay_checks import replay_checks_file
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.env import Context, check_depth, mid_episode_frames
from worldenv_core.models.checkpoint import read_config
from worldenv_core.parallel import run_jobs

log = logging.getLogger("worldenv.evaluate_imagination")


@dataclass
class PairedContext:
    start: RealStart  # where the real simulator starts
    context: Context  # what imagination starts from: the same frame, proprio and instruction
    kind: str  # "init" | "episode"


def start_frame(job: StartJob) -> dict:
    """The real frame and proprio at a benchmark init state (what imagination starts from)."""
    c = job.contract
    env = cached_env(c.suite, job.start.task_id, c.cameras, c.image_size, render=True)
    frame = restore(env, job.start)
    return {"start": job.start, "image": env.render([c.cameras[0]])[c.cameras[0]], "proprio": frame.proprio,
            "joint_pos": frame.joint_pos,
            "instruction": env.instruction}


def context_episodes(manifest, stage, contract: TaskContract, scale: str, worldsim: str, reflector: str,
                     source: str = "held_out") -> list[Path]:
    """Collected episodes the contexts start in. `held_out`: those neither the world model nor the
    reflector trained on (their checkpoints list their held-out episodes): the measurement.
    `training`: those the world model trained on, the reflector's held-out ones excepted: pairs
    that become a reflector's training data (`train_reflector train.pairs_from`), never a figure."""
    held = {}
    for path in (worldsim, reflector):
        keys = read_config(path)["meta"].get("held_out")
        if keys is None:
            raise ConfigError(f"{path} does not list the episodes it held out; retrain it to pair on its episodes")
        held[path] = set(keys)
    wmeta = read_config(worldsim)["meta"]
    expert_only = bool(wmeta.get("expert_only", False))
    try:  # the collections the world model read (its held-out list names episodes of those)
        paths = collected_episodes(manifest, stage, contract.name, scale, expert_only,
                                   wmeta.get("policy_collections", "latest"))
    except MissingEpisodesError:  # released checkpoints beside a re-collected expert set: contexts from the demos
        log.info("no policy rollouts collected here: mid-episode contexts from the expert demos only")
        paths = collected_episodes(manifest, stage, contract.name, scale, True)
    if source == "training":
        return [p for p in paths if episode_key(p) not in held[worldsim] | held[reflector]]
    return [p for p in paths if episode_key(p) in held[worldsim] & held[reflector]]


def build_contexts(cfg, contract: TaskContract, held: list[Path]) -> tuple[list[PairedContext], list[str]]:
    """init_states benchmark init states per task, then episode_frames frames (at contexts.depth) of the first
    episodes_per_task of `held` (the context episodes) of each task (and its first frame with
    `contexts.episode_start`); a mid-episode frame whose
    prefix does not replay to its recorded state is dropped here, before any imagination (its
    pairs could not be judged). -> (contexts, the dropped ones' errors)."""
    c, camera = cfg.contexts, contract.cameras[0]
    tasks = contract_task_ids(contract)
    jobs = [StartJob(contract, RealStart(task_id=t, init_state=i)) for t in tasks for i in range(c.init_states)]
    out = []
    for r in sorted(run_jobs(start_frame, jobs, workers=cfg.workers, launcher=cfg.launcher, desc="context frames",
                             ray_address=cfg.ray_address, progress=cfg.progress, unit="ctx"),
                    key=lambda r: (r["start"].task_id, r["start"].init_state)):
        ctx = Context(task_id=r["start"].task_id, instruction=r["instruction"],
                      frame=torch.from_numpy(r["image"]).permute(2, 0, 1).contiguous(), proprio=torch.from_numpy(r["proprio"]),
                      joint_pos=torch.from_numpy(r["joint_pos"]))
        out.append(PairedContext(r["start"], ctx, "init"))
    per_task: dict[int, int] = {}
    episodes = []
    for path in held:
        ep = read_episode(path, cameras=[camera], load_sim_state=False)
        t = ep.meta.task_id
        if t not in tasks or per_task.get(t, 0) >= c.episodes_per_task:
            continue
        per_task[t] = per_task.get(t, 0) + 1
        starts = [0] if c.episode_start else []  # where LOOP starts (its contexts are first frames)
        for f in starts + mid_episode_frames(ep.success, ep.length, c.episode_frames, check_depth(c.depth)):
            episodes.append(PairedContext(RealStart(task_id=t, seed=ep.meta.seed, episode=str(path), frame=f),
                                          Context.from_episode(ep, camera, f, contract.chunk), "episode"))
    errors = unreplayable(contract, [x.start for x in episodes], cache=replay_checks_file(cfg),
                          workers=cfg.workers, launcher=cfg.launcher,
                          ray_address=cfg.ray_address, progress=cfg.progress)
    for key, error in errors.items():
        log.warning("context dropped: %s", error)
    return out + [x for x in episodes if x.start.key not in errors], sorted(errors.values())
