"""What every stage does the same way: validate the task contract, resolve the config, seed,
find the experiment's manifest. One place, so stages stay thin."""

from __future__ import annotations

import logging
import os
import random
import secrets
import tempfile
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from worldenv_core.contract import TaskContract
from worldenv_core.errors import ConfigError
from worldenv_core.files import nearest_existing
from worldenv_core.envs.tasks import check_suite, resolve_task_ids, suite_max_steps
from worldenv_core.manifest import Manifest, config_hash

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
log = logging.getLogger("worldenv")
# A run's own id in its Hydra run folder's name (`${now:...}-${run_id:}`): two runs started in the
# same second never share a folder, whose files one of them would then overwrite under the other's record.
RUN_ID = f"{os.getpid()}-{secrets.token_hex(2)}"
if not OmegaConf.has_resolver("run_id"):
    OmegaConf.register_new_resolver("run_id", lambda: RUN_ID)


def available_tasks() -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / "task").glob("*.yaml"))


def require_task(cfg: DictConfig, registry: bool = True) -> DictConfig:
    """The task group is selected on the command line (`+task=libero_goal`); say so when it is not.
    `registry=False` on a host without the benchmark (a stage run from a pack: the suite and task ids
    were checked against the registry where the pack was made, and the pack's task is checked against
    this one on reading)."""
    task = cfg.get("task")
    if task is None:
        raise ConfigError(
            "no task selected: add +task=<name> to the command, e.g. `python -m stages.collect +task=libero_goal` "
            f"(valid tasks: {', '.join(available_tasks())}; +task=suite task.suite=<name> for any registered suite)"
        )
    if OmegaConf.is_missing(task, "suite"):
        raise ConfigError("task.suite has no value: add task.suite=<a registered LIBERO suite>, "
                          "e.g. +task=suite task.suite=libero_goal_swap")
    if registry:
        check_suite(task.suite)
        resolve_task_ids(task.suite, task.task_ids)
    if task.get("max_steps") is None:  # null: the standard horizon of the suite it derives from
        with open_dict(task):
            task.max_steps = suite_max_steps(task.suite)
    return task


def task_contract(cfg: DictConfig, registry: bool = True) -> TaskContract:
    """The run's task contract, built once from the validated `cfg.task`."""
    return TaskContract.from_config(require_task(cfg, registry))


def positive_int(cfg: DictConfig, key: str, allow_zero: bool = False) -> int:
    value = OmegaConf.select(cfg, key)
    ok = isinstance(value, int) and not isinstance(value, bool) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        raise ConfigError(f"{key} must be an integer {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return value


def group_size(cfg: DictConfig, key: str) -> int:
    """Rollouts per context at `key`: drawn as RLOO groups, whose baseline averages the other N - 1, so N >= 2."""
    value = OmegaConf.select(cfg, key)
    if not isinstance(value, int) or isinstance(value, bool) or value < 2:
        raise ConfigError(f"{key} must be at least 2 (each context's rollouts are an RLOO group: the baseline "
                          f"averages the other N - 1), got {value!r}")
    return value


def one_of(cfg: DictConfig, key: str, choices) -> str:
    """The setting at `key`, or a ConfigError naming it and its choices."""
    value = OmegaConf.select(cfg, key)
    if value not in choices:
        raise ConfigError(f"{key} must be one of {list(choices)}, got {value!r}")
    return value


def resolved(cfg: DictConfig) -> dict:
    """The config as plain data, without Hydra's own node (which holds machine paths)."""
    return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    try:
        import torch

        torch.manual_seed(seed)
    except ImportError:
        pass


def check_writable(key: str, path) -> None:
    """`path` (a folder a run will create or write) can be written, checked without creating it:
    a file made and removed in its nearest existing ancestor. Else one line naming the key."""
    probe = nearest_existing(path)
    if not probe.is_dir():
        raise ConfigError(f"{key} {path} is not writable: {probe} is a file, not a folder; give {key}=<a folder>")
    try:
        with tempfile.NamedTemporaryFile(dir=probe, prefix=".write_test"):
            pass
    except OSError as e:
        raise ConfigError(f"{key} {path} is not writable ({e.strerror or e} in {probe}): give a writable "
                          f"{key}=<folder>") from None


def experiment(cfg: DictConfig) -> Manifest:
    """The experiment directory (created, checked writable) and its manifest."""
    root = Path(cfg.experiment_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"experiment_dir {root} is not writable: {e}") from e
    check_writable("experiment_dir", root)  # distributed ranks probe it at once: each probe file has a name of its own
    return Manifest(root)


def setup_logging() -> None:
    logging.basicConfig(level=os.environ.get("WORLDENV_LOG", "INFO"),
                        format="[%(asctime)s %(name)s %(levelname)s] %(message)s", datefmt="%H:%M:%S")
    for noisy in ("robosuite", "OpenGL", "numba", "matplotlib"):
        logging.getLogger(noisy).setLevel(logging.ERROR)


def compose_config(stage: str, overrides=()) -> DictConfig:
    """A stage's config exactly as `python -m stages.<stage> <overrides...>` would see it, for
    running stages from Python (notebooks, tests): `run(compose_config("collect", ["+task=tiny"]))`."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(stage, overrides=list(overrides))


def start(cfg: DictConfig, validate) -> Manifest:
    """Every stage's prologue: logging, `validate(cfg)` (before anything is written), the
    experiment directory and its manifest, seeds."""
    setup_logging()
    validate(cfg)
    manifest = experiment(cfg)
    seed_everything(cfg.seed)
    return manifest


POLICY_SOURCES = {"sft": "train_policy", "post_trained": "post_train_loop"}


def resolve_checkpoint(stage_run, ref, producer: str, task: str, scale: str) -> str:
    """A model checkpoint folder: `ref` given as a folder, as a manifest record id, or (ref None)
    the latest `producer` record of this task and scale. The record becomes the run's input."""
    from worldenv_core.models.checkpoint import CONFIG, WEIGHTS, verify_checkpoint

    if ref and Path(str(ref)).is_dir():
        folder = verify_checkpoint(Path(str(ref)).resolve())
        for name in (WEIGHTS, CONFIG):  # what was used, by content, since no record vouches for it
            stage_run.record.input_files.append(stage_run.manifest.artefact(folder / name, kind="checkpoint"))
        return str(folder)
    if ref and ("/" in str(ref) or str(ref).startswith(".") or Path(str(ref)).exists()):
        raise ConfigError(f"no checkpoint folder at {ref}: give a folder holding {CONFIG} and {WEIGHTS}, a manifest "
                          f"record id, or leave it unset for the latest {producer}")
    record = stage_run.manifest.get(ref) if ref else stage_run.manifest.latest(producer, task=task, scale=scale)
    return str(stage_run.use(record, kind="checkpoint")[0].parent)


def resolve_policy(cfg: DictConfig, stage_run, contract: TaskContract | None = None) -> str:
    """`policy_from=`: sft (the latest train_policy; also null), post_trained (the latest
    post_train_loop), a checkpoint folder, or a record id. (Not `policy=`: that name is the
    policy-architecture config group, which Hydra would try to select.) `contract`: the run's
    (default: `task_contract(cfg)`)."""
    from worldenv_core.models.checkpoint import load_checkpoint

    ref = cfg.policy_from
    producer = POLICY_SOURCES.get(ref, "train_policy")
    path = resolve_checkpoint(stage_run, None if ref in POLICY_SOURCES else ref, producer, cfg.task.name, cfg.scale.name)
    # built once here, before any worker starts: its config, meta and weights agree with each other
    # and with the task (a wrong camera or width is one line now, not a traceback in every worker)
    load_checkpoint(path, "policy", contract or task_contract(cfg))
    return path


# Scale settings that choose how a result is evaluated, not what is trained (each stage's own
# copy, e.g. train_reflector's eta_folds, is left out of its work-dir name as well).
EVALUATION_ONLY_SCALE_KEYS = ("eta_folds", "rl_paired_contexts")
# Settings that do not define what is trained: how a run is watched, where the experiment lives
# (work dirs sit inside it, so a moved or copied experiment finds its finished work), and how a
# batch is split into micro-batches (a run resumes with another split, as with another world size).
NOT_NAMING_WORK_DIRS = ("logger", "experiment_dir", "accumulate")


def work_dir(experiment_dir, stage: str, config: dict, inputs: list[str]) -> Path:
    """Where a training stage keeps the checkpoints it resumes from, named by its settings and by
    the manifest records it read: rerun on other data (a newer collection, another policy) it
    starts fresh instead of resuming, or reusing, a run trained on something else."""
    config = {k: v for k, v in config.items() if k not in NOT_NAMING_WORK_DIRS}
    if isinstance(config.get("scale"), dict):
        config = {**config, "scale": {k: v for k, v in config["scale"].items() if k not in EVALUATION_ONLY_SCALE_KEYS}}
    return Path(experiment_dir) / stage / config_hash({**config, "inputs": sorted(inputs)})
