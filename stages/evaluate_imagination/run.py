"""Stage `evaluate_imagination`: does the imagined environment judge like the real one?

Each policy (at each Laplace noise scale) acts in imagination exactly as in post_train_loop
(the same imagined env, Laplace-sampled actions, reflector termination) from contexts no model
trained on; the actions of every imagined rollout are then executed open loop in the real
simulator from the same state (`envs.replay`), and optionally the policy also acts closed loop
there. The agreement of the imagined verdict with the real outcome of the same actions (AUROC,
F1, hack rate, timing, per task), the frames along the pairs and the world model as a policy
evaluator (Spearman, MAE over the policies) go into the manifest and the experiment report.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch
from omegaconf import DictConfig

from stages.evaluate_imagination.contexts import build_contexts, context_episodes
from stages.evaluate_imagination.evaluation import Variant, pair_variant, summarise, write_outputs
from stages.evaluate_imagination.judges import Judge, judge_pairs
from stages.report import write_report
from worldenv_core.data.selection import episode_key
from worldenv_core.files import write_text_atomic
from worldenv_core.imagination.env import build_imagined_env, check_depth
from worldenv_core.manifest import StageRun, config_hash, sha256_file
from worldenv_core.models.checkpoint import WEIGHTS, load_checkpoint, read_config
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.rl.termination import check_eta, reflector_eta
from worldenv_core.stage import (POLICY_SOURCES, ConfigError, group_size, positive_int, require_task, resolve_checkpoint,
                                 resolved, start, task_contract, work_dir)
from worldenv_core.training import pick_device

# 2: each benchmark init state's replays told apart by task. Pairs files and finished runs of an earlier
# pairing (every task's init-state contexts paired with one task's replays) are not reused: made again.
# 3: the reward model judging a mid-episode context's pairs is shown the recorded frames before it on both sides
# (`Context.history`, `replay.recorded_history`), as it was trained on whole prefixes.
PAIRING = 3
log = logging.getLogger("worldenv.evaluate_imagination")


LATER_CONTEXT_KEYS = {"source": "held_out", "episode_start": False, "depth": [0.0, 1.0]}


def episode_frames(cfg) -> int:
    """Contexts per context episode: its mid-episode frames, plus its first with episode_start."""
    return cfg.contexts.episode_frames + bool(cfg.contexts.episode_start)


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    positive_int(cfg, "horizon")
    group_size(cfg, "rollouts")  # drawn as LOOP draws them
    positive_int(cfg, "paired_policies")
    for key in ("closed_loop_rollouts", "gifs", "contexts.init_states", "contexts.episodes_per_task",
                "contexts.episode_frames"):
        positive_int(cfg, key, allow_zero=True)
    if cfg.contexts.source not in ("held_out", "training"):
        raise ConfigError(f"contexts.source must be held_out or training, got {cfg.contexts.source!r}")
    if cfg.contexts.source == "training" and (cfg.contexts.init_states or not cfg.contexts.episodes_per_task):
        raise ConfigError("contexts.source=training pairs from mid-episode frames of training episodes only (reflector "
                          "training data; the benchmark init states are the evaluations'): set contexts.init_states=0 "
                          "and contexts.episodes_per_task > 0")
    try:
        check_depth(cfg.contexts.depth)
    except ValueError as e:
        raise ConfigError(f"contexts.depth: {e}") from None
    if cfg.contexts.init_states > 50:
        raise ConfigError(f"contexts.init_states is at most 50 (the benchmark has 50 per task), got {cfg.contexts.init_states}")
    if not cfg.contexts.init_states and not (cfg.contexts.episodes_per_task and episode_frames(cfg)):
        raise ConfigError("no contexts: set contexts.init_states or contexts.episodes_per_task and contexts.episode_frames")
    if not cfg.policies or not cfg.noise_scales:
        raise ConfigError("policies and noise_scales must each name at least one")
    if any(not isinstance(n, (int, float)) or isinstance(n, bool) or n <= 0 for n in cfg.noise_scales):
        raise ConfigError(f"noise_scales must be positive numbers, got {list(cfg.noise_scales)}")
    bad = [h for h in cfg.horizons if not isinstance(h, int) or h <= 0 or h % cfg.task.chunk]
    if bad:
        raise ConfigError(f"horizons must be positive multiples of the chunk ({cfg.task.chunk}): {bad}")
    if cfg.more_reflectors and not cfg.store_frames:
        raise ConfigError("more_reflectors judge the stored frames of the pairs: set store_frames=true")
    if cfg.sampler_noise is not None and not 0 <= cfg.sampler_noise <= 1:
        raise ConfigError(f"sampler_noise must be in [0, 1] (null: the world model's own), got {cfg.sampler_noise}")
    try:
        if cfg.eta is not None:
            check_eta(cfg.eta)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    contract, device = task_contract(cfg), pick_device(cfg.device)
    config = resolved(cfg)
    tags = {"task": contract.name, "scale": cfg.scale.name}
    with StageRun(manifest, "evaluate_imagination", tags, config) as stage:
        worldsim = resolve_checkpoint(stage, cfg.worldsim_from, "train_worldsim", contract.name, cfg.scale.name)
        reflector = resolve_checkpoint(stage, cfg.reflector_from, "train_reflector", contract.name, cfg.scale.name)
        eta = reflector_eta(reflector, cfg.eta)
        variants = [Variant(name=f"{ref}@{float(n):g}", path=resolve_checkpoint(
                        stage, None if ref in POLICY_SOURCES else ref, POLICY_SOURCES.get(ref, "train_policy"),
                        contract.name, cfg.scale.name), noise_scale=float(n))
                    for ref in cfg.policies for n in cfg.noise_scales]
        variants = [Variant(v.name, v.path, v.noise_scale, paired=i < cfg.paired_policies) for i, v in enumerate(variants)]
        stage.record.tags.update({"eta": eta, "sampling_steps": cfg.sampling_steps, "sampler_noise": cfg.sampler_noise,
                                  "worldsim": _name(worldsim), "reflector": _name(reflector)})
        if cfg.contexts.source == "training":  # reflector training data, not a measurement: the report tells them apart
            stage.record.tags["contexts"] = "training"
        # init-state contexts alone need no recorded episode: checkpoint folders are enough
        held = (context_episodes(manifest, stage, contract, cfg.scale.name, worldsim, reflector, cfg.contexts.source)
                if cfg.contexts.episodes_per_task and episode_frames(cfg) else [])
        # a run made before the pairing fix is not one this would repeat
        if (done := stage.finished_before(same=lambda rec: rec.metrics.get("pairing") == PAIRING)) is not None:
            return done.metrics
        encoder = InstructionEncoder()
        encode = lambda s: encoder(s).to(device)  # noqa: E731
        env, camera = build_imagined_env(worldsim, reflector, eta, encode, cfg.horizon, cfg.sampling_steps, device, contract,
                                         cfg.sampler_noise)
        if camera != contract.cameras[0]:
            raise ConfigError(f"the world model imagines {camera!r} but task {contract.name} renders {contract.cameras[0]!r} first")
        contexts, dropped = build_contexts(cfg, contract, held)
        if not contexts:
            raise ConfigError(f"no context left: every mid-episode frame failed to replay ({dropped[0]})")
        log.info("paired replay of %d policies x %d contexts (%d init states, %d in recorded episodes) x %d rollouts; eta %.2f; "
                 "world model %s, reflector %s", len(variants), len(contexts), sum(c.kind == "init" for c in contexts),
                 sum(c.kind == "episode" for c in contexts), cfg.rollouts, eta, worldsim, reflector)
        # Each policy's pairs are kept as they finish: a killed run re-run skips the policies done.
        shown = ("policies", "noise_scales", "paired_policies", "progress", "workers", "launcher", "ray_address", "gifs",
                 "more_reflectors", "store_frames")  # judges score stored pairs: naming more reuses them
        key = {k: v for k, v in config.items() if k not in shown}
        # settings added later name no work dir at their defaults: the pairs made before them stay found
        key["contexts"] = {k: v for k, v in key["contexts"].items() if LATER_CONTEXT_KEYS.get(k, ...) != v}
        work = work_dir(cfg.experiment_dir, "evaluate_imagination", key, stage.work_inputs())
        stage.lock(work)
        judges = further_reflectors(cfg, stage, contract, camera, contexts)  # after the work dir: not part of its name
        results, instructions = {}, {c.context.task_id: c.context.instruction for c in contexts}
        pasts = {c.start.key: c.context.history for c in contexts}  # what the further judges are shown too
        for i, v in enumerate(variants):
            path = work / f"{variant_key(v)}.json"
            frames = work / "frames" / path.stem if cfg.store_frames else None
            if path.exists():
                results[v.name] = json.loads(path.read_text())
                log.info("%s: paired earlier (%s)", v.name, path)
            else:
                torch.manual_seed(cfg.seed)
                results[v.name] = pair_variant(cfg, contract, v, env, contexts, encode, reflector, eta, device,
                                               gifs=cfg.gifs if i == 0 else 0, out=work, frames_dir=frames)
                _write_json(path, results[v.name])
            if v.paired and judges and judge_pairs(
                    results[v.name]["rows"], frames, judges,
                    lambda j: load_checkpoint(j.path, "reflector", contract, device=str(device))[0],
                    lambda row: instructions[row["task_id"]], encode, lambda row: pasts.get(row["start"])):
                _write_json(path, results[v.name])  # the judges' scores kept: named again, they cost nothing
        summary = summarise(results, [v.name for v in variants], eta, list(cfg.horizons), tuple(judges))
        # the prefix checks reset the real simulator too; a dropped context is named, not hidden
        summary["real_episodes"] += sum(c.kind == "episode" for c in contexts) + len(dropped)
        summary["contexts_dropped"] = dropped
        write_outputs(stage, summary, results, work)
        stage.metrics.update({k: v for k, v in summary.items() if k not in ("per_policy", "per_task", "frames", "judges")},
                             pairing=PAIRING)
        log.info("verdict fidelity of %s: %s", variants[0].name, json.dumps(summary["headline"]))
    report = write_report(manifest.root, contract.name)
    log.info("experiment report: %s", report)
    return summary


def further_reflectors(cfg, stage, contract, camera: str, contexts) -> list[Judge]:
    """`more_reflectors`, each at its own eta; refused if it watches another camera or trained on an
    episode a context starts in."""
    judges = []
    episodes = {episode_key(c.start.episode) for c in contexts if c.start.episode}
    for ref in cfg.more_reflectors:
        path = resolve_checkpoint(stage, ref, "train_reflector", contract.name, cfg.scale.name)
        meta = read_config(path)["meta"]
        if meta["camera"] != camera:
            raise ConfigError(f"more_reflectors: {ref} watches {meta['camera']!r}, the world model imagines {camera!r}")
        seen = episodes - set(meta.get("held_out") or [])
        if seen:
            raise ConfigError(f"more_reflectors: {ref} trained on episodes the contexts start in ({sorted(seen)[:3]}); "
                              "train it with the same holdout_every as the reflector")
        judges.append(Judge(_name(path), path, reflector_eta(path, None)))
    return judges


def variant_key(v: Variant) -> str:
    """A policy variant's pairs file in the work dir, named by the policy's weights (by content: the
    same checkpoint from another clone, worktree or folder finds its pairs), noise and pairing."""
    return pairs_key(sha256_file(Path(v.path) / WEIGHTS), v.noise_scale, v.paired)


def pairs_key(weights_sha256: str, noise_scale: float = 1.0, paired: bool = True) -> str:
    """The pairs file's name for a policy's weights (by their hash), noise scale and pairing (`PAIRING`)."""
    return config_hash({"policy": weights_sha256, "noise": float(noise_scale), "paired": paired, "pairing": PAIRING})


def _name(checkpoint: str) -> str:
    """A checkpoint as the report names it: its folder with the one above (a run's work dir and
    `reflector`, or a released `libero_goal/reflector_imagined`)."""
    p = Path(checkpoint)
    return f"{p.parent.name}/{p.name}"


def _write_json(path: Path, data) -> None:
    write_text_atomic(path, json.dumps(data))
