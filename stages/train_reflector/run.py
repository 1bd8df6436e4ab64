"""Stage `train_reflector`: the instant reflector (paper sec. 4.2, appendix B.3).

Trains R(o_{1:t}, g) with binary cross-entropy on the oracle's per-step labels y_t, from the
expert demos and the policy's rollouts in the manifest, half positive and half negative prefixes
per batch. Then measures it on held-out real episodes and on the world simulator's open-loop
replays of the same episodes: per-step accuracy/F1/AUROC at eta, and termination (correct stops,
false stops, missed successes, timing error), with R(t) plots.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from stages.train_reflector.evaluation import evaluate_held_out, headline
from stages.train_reflector.training import cross_validate_eta, fit, imagined_copies
from worldenv_core.data.selection import POLICY_COLLECTIONS, collected_episodes, episode_key, load_split
from worldenv_core.imagination.pairs import (calibration_rows, calibration_starts, checked_episodes, eta_on_pairs,
                                            pair_past)
from worldenv_core.imagination.verdict import ETA_GRID, rescored
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import save_model
from worldenv_core.rl.termination import check_eta
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.stage import (ConfigError, one_of, positive_int, require_task, resolve_checkpoint, resolved, start,
                                 task_contract, work_dir)
from worldenv_core.training import pick_device, record_checkpoint, trainer_options
from worldenv_core.viz import plot_history

log = logging.getLogger("worldenv.train_reflector")


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("train.steps", "train.batch_size", "train.log_every", "train.checkpoint_every", "holdout_every",
                "frame_stride", "reflector.max_frames"):
        positive_int(cfg, key)
    positive_int(cfg, "train.label_delay", allow_zero=True)
    positive_int(cfg, "eta_folds", allow_zero=True)
    one_of(cfg, "policy_collections", POLICY_COLLECTIONS)
    if cfg.eta_folds == 1:
        raise ConfigError("eta_folds must be 0 (eta as configured) or at least 2 (K-fold cross-validation), got 1")
    try:
        check_eta(cfg.eta)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.camera not in cfg.task.cameras:
        raise ConfigError(f"camera {cfg.camera!r} is not one of the task's cameras {list(cfg.task.cameras)}")
    if not 0.0 <= cfg.train.hard_negative_fraction <= 1.0:
        raise ConfigError(f"train.hard_negative_fraction must be in [0, 1], got {cfg.train.hard_negative_fraction}")
    if cfg.train.mine.every < 0 or (cfg.train.mine.every and cfg.train.checkpoint_every % cfg.train.mine.every):
        raise ConfigError(f"train.mine.every must be 0 (off) or divide train.checkpoint_every "
                          f"({cfg.train.checkpoint_every}) so a resumed run mines what it mined; got {cfg.train.mine.every}")
    if not 0.0 <= cfg.train.mine.threshold <= 1.0:
        raise ConfigError(f"train.mine.threshold must be in [0, 1], got {cfg.train.mine.threshold}")
    positive_int(cfg, "train.pairs_eta_every", allow_zero=True)
    if cfg.train.pairs_eta_every and not cfg.train.pairs_from:
        raise ConfigError("train.pairs_eta_every sets pairs aside to choose eta: give the pairs (train.pairs_from)")
    if cfg.train.pairs_from and cfg.eta_folds:
        raise ConfigError("train.pairs_from with eta_folds: the folds split real episodes, not pairs; train with "
                          "eta_folds=0 and read the eta chosen on held-out replays off evaluate_imagination's report")
    trainer_options(cfg, "train.batch_size")
    if cfg.train.batch_size < 2:
        raise ConfigError("train.batch_size must be at least 2 (half positives, half negatives)")


def sees_world_latent(cfg) -> bool:
    """The reflector `worldsim_latent`: its frame encoder is a world model's autoencoder."""
    target = OmegaConf.select(cfg, "reflector.frame_encoder._target_", default="") or ""
    return target.endswith("WorldModelLatentBackbone")


def describe_training(cfg) -> str:
    """How the reflector was trained, in words, for the report (kept in the record's metrics)."""
    mine = cfg.train.mine
    return ", ".join([f"{cfg.train.steps} steps", f"label delay {cfg.train.label_delay}",
                      f"mining every {mine.every} > {mine.threshold}" if mine.every else "no mining"]
                     + (["+ imagined replays"] if cfg.train.with_imagined else [])
                     + (["+ paired rollouts (real labels)"] if cfg.train.pairs_from else [])
                     + (["on the world model's latent"] if sees_world_latent(cfg) else []))


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    contract = task_contract(cfg)
    device = pick_device(cfg.device)
    # policy_collections came later: at its default a run keeps its settings hash and work dir
    config = {k: v for k, v in resolved(cfg).items() if not (k == "policy_collections" and v == "latest")}
    tags = {"task": contract.name, "scale": cfg.scale.name, "data": "expert" if cfg.expert_only else "expert+policy",
            "hard_negatives": "mined" if cfg.train.mine.every else "off"}
    with StageRun(manifest, "train_reflector", tags, config) as stage:
        paths = collected_episodes(manifest, stage, contract.name, cfg.scale.name, cfg.expert_only,
                                   cfg.policy_collections)
        train_paths, held, episodes, held_eps = load_split(paths, cfg.holdout_every, cfg.camera)
        key = {k: v for k, v in config.items() if k not in ("imagined", "plots", "eta_folds")}
        # train.with_imagined is named by the world model it imagines with (below), if on; pairs_from by
        # the pair folders, if any (so a reflector trained without pairs keeps its work dir)
        key["train"] = {k: v for k, v in key["train"].items() if k not in ("with_imagined", "pairs_from")
                        and not (k == "pairs_eta_every" and not v)}  # added later: off keeps old work dirs
        instructions = {ep.meta.task_id: ep.meta.instruction for ep in episodes}
        pairs, pair_folders, calibration = paired_training(cfg, stage, instructions, held)
        if pair_folders:
            key["train"]["pairs_from"] = pair_folders
        dreamed, worldsim = None, None
        if cfg.train.with_imagined or sees_world_latent(cfg):  # the world model it imagines with (or sees through)
            worldsim = resolve_checkpoint(stage, cfg.imagined.worldsim_from, "train_worldsim", contract.name,
                                          cfg.scale.name)
            key["imagined_from"] = Path(worldsim).parent.name
        if (done := stage.finished_before()) is not None:
            return done.metrics
        if cfg.train.with_imagined:  # the world simulator's replays of the training episodes, real labels
            dreamed = imagined_copies(cfg, contract, worldsim, episodes)
        # named by what defines the training and its inputs, not by how it is evaluated, shown or
        # how eta is chosen: changing imagined.*, plots or eta_folds re-evaluates a finished run
        key["held_out"] = [episode_key(p) for p in held]  # a work dir and its weights' split cannot disagree
        work = work_dir(cfg.experiment_dir, "train_reflector", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        encoder = InstructionEncoder()
        t0 = time.perf_counter()
        model, model_cfg, meta, history = fit(cfg, contract, episodes + (dreamed or []) + pairs, work, device, encoder,
                                              {"held_out": [episode_key(p) for p in held],
                                               "imagined_episodes": len(dreamed or []), "paired_episodes": len(pairs)},
                                              worldsim=worldsim)
        stage.record.tags["reward"] = model.reward_kind
        if history:
            stage.add_output(plot_history(history, work / "losses.png", f"train_reflector {contract.name}"), kind="plot")
        train_s = time.perf_counter() - t0
        cv = None
        if cfg.eta_folds:
            t2 = time.perf_counter()
            cv = cross_validate_eta(cfg, contract, train_paths, episodes, work, device, encoder, dreamed, worldsim)
            cv["wall_s"] = round(time.perf_counter() - t2, 1)
        # the checkpoint carries the threshold to use it at (evaluate / post_train_loop with eta=null);
        # a cross-validated one is its own folder, so the plain one (and records naming it) stay as they are
        eta, chosen_by = (cv["chosen_eta"], f"{cfg.eta_folds}-fold cross-validation") if cv else (float(cfg.eta), "config")
        on_pairs = None
        if calibration:  # train.pairs_eta_every: the verdict's F1 on pairs it did not train on
            on_pairs = eta_on_pairs(calibration, lambda row, frames: rescored(  # judged as the imagined env will
                model, instructions[int(row["task_id"])], frames, encoder, pair_past(row, contract.cameras[0], contract.chunk)),
                ETA_GRID, float(cfg.eta))
            (work / "eta_on_pairs.json").write_text(json.dumps(on_pairs, indent=2))
            stage.add_output(work / "eta_on_pairs.json", kind="report")
            eta, chosen_by = on_pairs["chosen_eta"], f"verdict F1 on {on_pairs['pairs']} held-out training pairs"
            log.info("eta %.2f chosen on %d held-out training pairs (F1 %.3f, hack rate %.3f there)", eta,
                     on_pairs["pairs"], on_pairs["at_chosen"]["f1"], on_pairs["at_chosen"]["hack_rate"])
        final = save_model(work / ("reflector" if cv is None else f"reflector-cv{cfg.eta_folds}"), model, model_cfg,
                           {**meta, "eta": eta, "eta_chosen_by": chosen_by, "step": cfg.train.steps})
        record_checkpoint(stage, final)
        t1 = time.perf_counter()
        report = evaluate_held_out(cfg, contract, stage, model, encoder, held, held_eps, cv, work)
        plots = ["reflector_curves.png"] + (["reflector_by_lead.png"] if "imagined_by_lead" in report else [])
        for name in ("reflector_eval.json", "reflector_eval.md", *plots):
            stage.add_output(work / name, kind="report" if name.endswith(("json", "md")) else "plot")
        stage.metrics.update({"episodes": len(episodes), "held_out": len(held_eps), "steps": cfg.train.steps,
                              "paired_episodes": len(pairs), "eta": eta, "eta_chosen_by": chosen_by,
                              **({"eta_pairs": on_pairs["pairs"]} if on_pairs else {}),
                              "training": describe_training(cfg), "train_wall_s": round(train_s, 1),
                              "eval_wall_s": round(time.perf_counter() - t1, 1), "device": str(device),
                              "ranks": meta.get("ranks", 1),
                              **headline(report)})
        log.info("reflector saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics


def paired_training(cfg, stage, instructions: dict[int, str], held: list[Path]) -> tuple[list, list[str], list]:
    """`train.pairs_from`: both sides of each stored pair, labelled by the real outcome
    (`imagination.pairs`), the pair folders' names (part of the work dir's), and the pairs set aside
    to choose eta (`train.pairs_eta_every`). Refused before any training when a pair starts where an
    evaluation judges (its held-out episodes, init states). `instructions`: the training episodes'
    by task."""
    forbidden = {episode_key(p) for p in held}
    folders = [pair_folder(stage, ref) for ref in cfg.train.pairs_from]
    pairs = []
    try:
        set_aside = calibration_starts(folders, int(cfg.train.pairs_eta_every))
        past_of = lambda row: pair_past(row, cfg.task.cameras[0], int(cfg.task.chunk))  # noqa: E731
        per_folder = [(folder, checked_episodes(folder, instructions, forbidden, set_aside, past_of))
                      for folder in folders]
    except (ValueError, FileNotFoundError) as e:
        raise ConfigError(f"train.pairs_from: {e}") from None
    for folder, got in per_folder:
        log.info("%s: %d paired rollouts (%d real successes), both sides", folder, len(got) // 2,
                 sum(ep.success.any() for ep in got) // 2)
        pairs += got
    calibration = calibration_rows(folders, set_aside)
    if set_aside:
        log.info("%d pairs from %d training episodes set aside to choose eta", len(calibration), len(set_aside))
    return pairs, [f.name for f in folders], calibration


def pair_folder(stage, ref) -> Path:
    """A `train.pairs_from` entry as the evaluate_imagination work dir holding its pairs."""
    folder = Path(str(ref))
    if not folder.is_dir():  # a record id: its pairs.json sits in the work dir beside the stored frames
        record = stage.manifest.get(str(ref))
        if record.stage != "evaluate_imagination":
            raise ConfigError(f"train.pairs_from: {ref} is a {record.stage} record, not evaluate_imagination's")
        folder = next(p for p in stage.use(record, kind="report") if p.name == "pairs.json").parent
    return folder
