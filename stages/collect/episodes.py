"""Where a collection's episodes live: one folder per data-defining configuration, named by its
hash (a different seed, camera set, resolution or expert gets its own folder, so resuming never
mixes episodes of two configurations)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from omegaconf import DictConfig, ListConfig

from worldenv_core.envs.libero_env import ARM_START_NOISE
from worldenv_core.manifest import config_hash


def expert_code_hash() -> str:
    """Hash of every ``*.py`` of the expert package, subpackages included (expert/articulated/).

    Each file counts with its path relative to the package, so moving code between files is a
    change too. (Recursive since the articulated split: that changed the hash of every expert
    collection, so they are collected again into a new folder, on purpose.)"""
    import worldenv_core.envs.expert as expert

    root = Path(expert.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py"), key=lambda f: f.relative_to(root).as_posix()):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
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
    if cfg.init_states == "sampled":  # the arm's start noise (sampled resets before it kept the nominal pose)
        defining["arm_start_noise"] = ARM_START_NOISE
    if cfg.source == "expert":  # episodes of a changed expert are other episodes: never mix them
        defining["expert_code"] = expert_code_hash()
    if cfg.source == "policy":
        noise = cfg.noise_scale  # a number as before (earlier collections keep their folders), or a list
        defining.update(policy=str(cfg.policy_from), noise_scale=list(noise) if isinstance(noise, ListConfig) else noise,
                        stop_on_success=cfg.stop_on_success)
    if cfg.source == "lerobot":
        defining["import"] = [str(cfg.lerobot_import.root), cfg.lerobot_import.repo_id, cfg.lerobot_import.max_episodes]
    return Path(cfg.data_dir) / task.name / f"{cfg.source}-{config_hash(defining)[:8]}"
