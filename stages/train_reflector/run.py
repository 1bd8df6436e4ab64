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
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from worldenv_core.data.selection import episode_key, load_split
from worldenv_core.manifest import ArtefactError, StageRun
from worldenv_core.metrics import binary_metrics
from worldenv_core.models.checkpoint import save_model
from worldenv_core.models.reflector import check_eta, prefix_scores, score_prefixes
from worldenv_core.models.reflector_data import PrefixSampler
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.rl.termination import StopOutcome, best_eta, check_steps, first_stop, first_success, success_labels, termination_metrics
from worldenv_core.stage import ConfigError, positive_int, require_task, resolve_checkpoint, resolved, start, work_dir
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Checkpoints, RunningMeans, pick_device, plot_history, random_shift

log = logging.getLogger("worldenv.train_reflector")
ETA_SWEEP = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("train.steps", "train.batch_size", "train.log_every", "train.checkpoint_every", "holdout_every",
                "frame_stride", "reflector.max_frames"):
        positive_int(cfg, key)
    positive_int(cfg, "train.label_delay", allow_zero=True)
    positive_int(cfg, "eta_folds", allow_zero=True)
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
    if cfg.train.batch_size < 2:
        raise ConfigError("train.batch_size must be at least 2 (half positives, half negatives)")


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task = cfg.task
    device = pick_device(cfg.device)
    config = resolved(cfg)
    tags = {"task": task.name, "scale": cfg.scale.name, "data": "expert" if cfg.expert_only else "expert+policy"}
    with StageRun(manifest, "train_reflector", tags, config) as stage:
        train_paths, held, episodes, held_eps = load_split(manifest, stage, cfg)
        key = {k: v for k, v in config.items() if k not in ("imagined", "plots", "eta_folds")}
        # train.with_imagined is named by the world model it imagines with (below), if on
        key["train"] = {k: v for k, v in key["train"].items() if k != "with_imagined"}
        dreamed = None
        if cfg.train.with_imagined:  # the world simulator's replays of the training episodes, real labels
            worldsim = resolve_checkpoint(stage, cfg.imagined.worldsim_from, "train_worldsim", task.name, cfg.scale.name)
            dreamed = imagined_copies(cfg, worldsim, episodes)
            key["imagined_from"] = Path(worldsim).parent.name
        # named by what defines the training and its inputs, not by how it is evaluated, shown or
        # how eta is chosen: changing imagined.*, plots or eta_folds re-evaluates a finished run
        work = work_dir(cfg.experiment_dir, "train_reflector", key, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        encoder = InstructionEncoder()
        t0 = time.perf_counter()
        model, model_cfg, meta, history = fit(cfg, episodes + (dreamed or []), work, device, encoder,
                                              {"held_out": [episode_key(p) for p in held],
                                               "imagined_episodes": len(dreamed or [])})
        if history:
            stage.add_output(plot_history(history, work / "losses.png", f"train_reflector {task.name}"), kind="plot")
        train_s = time.perf_counter() - t0
        cv = None
        if cfg.eta_folds:
            t2 = time.perf_counter()
            cv = cross_validate_eta(cfg, train_paths, episodes, work, device, encoder, dreamed)
            cv["wall_s"] = round(time.perf_counter() - t2, 1)
        # the checkpoint carries the threshold to use it at (evaluate / post_train_loop with eta=null);
        # a cross-validated one is its own folder, so the plain one (and records naming it) stay as they are
        eta, chosen_by = (cv["chosen_eta"], f"{cfg.eta_folds}-fold cross-validation") if cv else (float(cfg.eta), "config")
        final = save_model(work / ("reflector" if cv is None else f"reflector-cv{cfg.eta_folds}"), model, model_cfg,
                           {**meta, "eta": eta, "eta_chosen_by": chosen_by, "step": cfg.train.steps})
        for f in sorted(final.iterdir()):
            stage.add_output(f, kind="checkpoint")

        t1 = time.perf_counter()
        videos = {"real": [ep.video(cfg.camera) for ep in held_eps]}
        imagined_eps = held_eps
        if cfg.imagined.enabled:
            imagined = imagine_held_out(cfg, stage, held, held_eps)
            if imagined is not None:
                imagined_eps, videos["imagined"] = imagined
        report = {"eta": float(cfg.eta), "held_out_episodes": len(held_eps)}
        curves = {}
        for kind, vids in videos.items():
            eps = held_eps if kind == "real" else imagined_eps
            report[kind], curves[kind] = evaluate_videos(model, encoder, eps, vids, cfg.frame_stride, cfg.eta)
        report["eval_wall_s"] = round(time.perf_counter() - t1, 1)
        if cv is not None:  # the held-out episodes chose nothing: judged at the chosen eta off their curves
            cv["real_termination_at_chosen_eta"] = termination_at(held_eps, curves["real"], cv["chosen_eta"])
            report["cross_validation"] = cv
        write_report(report, curves, held_eps, imagined_eps, cfg, work)
        for name in ("reflector_eval.json", "reflector_eval.md", "reflector_curves.png"):
            stage.add_output(work / name, kind="report" if name.endswith(("json", "md")) else "plot")
        stage.metrics.update({"episodes": len(episodes), "held_out": len(held_eps), "steps": cfg.train.steps,
                              "train_wall_s": round(train_s, 1), "device": str(device), **_headline(report)})
        log.info("reflector saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics


def fit(cfg, episodes: list, work: Path, device, encoder, meta_extra: dict, overall=None):
    """Train (or resume, or find finished in `work`) a reflector on `episodes`; `overall`: a
    progress bar over several fits (the cross-validation's) that this one's steps advance.
    -> (model on the CPU in eval mode, its config, its meta, the loss history; [] when untrainable)."""
    try:
        sampler = PrefixSampler(episodes, cfg.camera, cfg.frame_stride, cfg.reflector.max_frames,
                                cfg.train.hard_negative_fraction, cfg.train.hard_window, cfg.train.label_delay)
    except ValueError as e:
        raise ConfigError(f"{e}; collect more episodes (policy rollouts give failures)") from None
    model_cfg = OmegaConf.to_container(cfg.reflector, resolve=True)
    model = instantiate(model_cfg, _convert_="all").to(device)
    task = cfg.task
    meta = {"kind": "reflector", "task": task.name, "suite": task.suite, "camera": cfg.camera,
            "image_size": task.image_size, "frame_stride": cfg.frame_stride, "eta": float(cfg.eta),
            "label_delay": cfg.train.label_delay, "episodes": len(episodes), **meta_extra, **sampler.counts()}
    history = []
    if getattr(model, "trainable", True):
        log.info("training on %d episodes (%s) for %d steps on %s; work dir %s", len(episodes), sampler.counts(),
                 cfg.train.steps, device, work)
        history = train(cfg, model, model_cfg, meta, sampler, encoder, work, device, overall)
    else:  # the VLM yes/no mode: nothing to train, its checkpoint is the config naming the VLM
        log.info("%s has nothing to train", type(model).__name__)
    return model.cpu().eval(), model_cfg, meta, history


def cross_validation_folds(paths: list[Path], folds: int) -> list[list[int]]:
    """K folds of the training episodes (indices), every K-th in sorted path order, so each fold
    mixes tasks and sources like the whole; a fold must leave something to train on."""
    if folds > len(paths) or folds < 2:
        raise ConfigError(f"eta_folds={folds} needs 2 <= folds <= the {len(paths)} training episodes "
                          f"(eta_folds=0 keeps the configured eta)")
    order = sorted(range(len(paths)), key=lambda i: paths[i])
    return [order[k::folds] for k in range(folds)]


def cross_validate_eta(cfg, paths: list[Path], episodes: list, work: Path, device, encoder,
                       dreamed: list | None = None) -> dict:
    """Choose eta by K-fold cross-validation over the training episodes: K reflectors, each trained
    without one fold (in work/folds/, resumable), score the fold they did not see; eta is the one
    with the best termination F1 over all those out-of-fold episodes. `dreamed`: imagined copies
    of `episodes` (train.with_imagined), trained on with their fold; scoring is on real video."""
    folds = cross_validation_folds(paths, cfg.eta_folds)
    scored, curves = [], []  # every training episode once, by the reflector that did not train on it
    overall = tqdm(total=len(folds) * cfg.train.steps, desc=f"eta cross-validation ({len(folds)} folds)",
                   unit="step", dynamic_ncols=True, position=0)
    for k, fold in enumerate(folds):
        keep = set(fold)
        fit_eps = [ep for i, ep in enumerate(episodes) if i not in keep]
        fit_eps += [ep for i, ep in enumerate(dreamed or []) if i not in keep]
        val_eps = [episodes[i] for i in fold]
        log.info("eta cross-validation: fold %d of %d (%d episodes held out of %d)", k + 1, len(folds),
                 len(val_eps), len(episodes))
        model, *_ = fit(cfg, fit_eps, work / "folds" / f"{k + 1}-of-{len(folds)}", device, encoder,
                        {"held_out": [episode_key(paths[i]) for i in fold]}, overall)
        _, fold_curves = evaluate_videos(model, encoder, val_eps, [ep.video(cfg.camera) for ep in val_eps],
                                         cfg.frame_stride, cfg.eta)
        scored += val_eps
        curves += fold_curves
    overall.close()
    sweep = {str(e): termination_at(scored, curves, e) for e in ETA_SWEEP}
    return {"folds": len(folds), "episodes": len(episodes),
            "eta_sweep": {e: {"termination_f1": m["f1"], "episodes": m["episodes"], "false_stops": m["false_stops"],
                              "missed_successes": m["missed_successes"]} for e, m in sweep.items()},
            "chosen_eta": best_eta({e: m["f1"] for e, m in sweep.items()}, cfg.eta)}


def termination_at(episodes, curves, eta: float) -> dict:
    """Termination metrics of already scored (steps, R) curves at another eta."""
    return termination_metrics([StopOutcome(first_success(ep.success), first_stop(steps, scores, eta))
                                for ep, (steps, scores) in zip(episodes, curves)])


def train(cfg, model, model_cfg: dict, meta: dict, sampler: PrefixSampler, encoder, work: Path, device,
          overall=None) -> list[dict]:
    """BCE on balanced prefixes; resumes from the work dir's last checkpoint. Returns the history."""
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.train.lr,
                            weight_decay=cfg.train.weight_decay)
    ckpts = Checkpoints(work)
    step, history = ckpts.restore(model, {"reflector": opt})
    total = cfg.train.steps
    mine_every = cfg.train.mine.every
    if mine_every and mine_every <= step < total:  # resumed: the hard set the run had (checkpoints fall on mining steps)
        _mine(cfg, model, sampler, encoder, device, step - step % mine_every)
    if overall is not None:
        overall.update(step)  # what earlier sittings (or a finished fold) did
    bar = tqdm(range(step, total), initial=step, total=total, desc="train_reflector", dynamic_ncols=True,
               position=0 if overall is None else 1, leave=overall is None)
    tracker = make_tracker(cfg, work, "train_reflector")
    running = RunningMeans(history, cfg.train.log_every, bar, tracker)
    for step in bar:
        model.train()
        b = sampler.batch(cfg.train.batch_size, seed=cfg.seed * 1_000_003 + step)  # by step: resumes exactly
        frames, mask = _augment(model, b["frames"], b["mask"], cfg.train.augment_shift,
                                torch.Generator().manual_seed(cfg.seed * 7_000_003 + step))
        logits = model(frames.to(device), mask.to(device), encoder(b["instruction"]).to(device))
        label = b["label"].to(device)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, label)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        running.add(bce=loss.item(), batch_accuracy=((logits > 0).float() == label).float().mean().item())
        done = step + 1
        running.end_step(done, total)
        if overall is not None:
            overall.update(1)
        if mine_every and done % mine_every == 0 and done < total:
            _mine(cfg, model, sampler, encoder, device, done)
        if done % cfg.train.checkpoint_every == 0 or done == total:
            ckpts.save(done, model, model_cfg, meta, {"reflector": opt}, history)
    bar.close()
    tracker.close()
    return history


def _mine(cfg, model, sampler: PrefixSampler, encoder, device, step: int) -> None:
    """Score every training episode's negative chunk boundaries with the current model and make
    the high-scoring ones (near misses) hard negatives until the next mining."""
    model.eval()
    lang = encoder(sampler.instructions).to(device)
    mined = sampler.mine(lambda i, frames, steps: score_prefixes(model, frames.to(device), lang[i], steps).cpu(),
                         cfg.train.mine.threshold)
    sampler.set_mined(mined)
    log.info("step %d: %d negative frames scored above %.2f are hard negatives now (%d in all)", step, len(mined),
             cfg.train.mine.threshold, len(sampler.hard))


def _augment(model, frames: torch.Tensor, mask: torch.Tensor, shift: int, generator: torch.Generator):
    """Resize the real frames to the model's input size first (the shift is then cheap), then shift
    each by up to `shift` pixels of the original resolution."""
    x = frames[mask].float() / 255.0
    size = model.input_size or x.shape[-1]
    if size != x.shape[-1]:
        x = torch.nn.functional.interpolate(x, size=(size, size), mode="area")
    pad = round(shift * size / frames.shape[-1])
    out = torch.zeros(*mask.shape, *x.shape[1:])
    out[mask] = random_shift(x, pad, generator) if pad else x
    return out, mask


def imagine_held_out(cfg, stage: StageRun, held: list[Path], held_eps):
    """World-simulator replays of the held-out episodes the world model did not train on, or None
    when the experiment has no world simulator yet. `imagined.worldsim_from`: a train_worldsim
    record id or checkpoint folder; null = the latest of this task and scale."""
    from worldenv_core.models.checkpoint import read_config

    ref = cfg.imagined.worldsim_from
    try:
        ckpt = resolve_checkpoint(stage, ref, "train_worldsim", cfg.task.name, cfg.scale.name)
    except ArtefactError:
        if ref is not None:  # a named world model that is not there is an error, not a skip
            raise
        log.warning("no train_worldsim record in %s: imagined evaluation skipped", cfg.experiment_dir)
        return None
    unseen = read_config(ckpt)["meta"].get("held_out")
    eps = [ep for p, ep in zip(held, held_eps) if unseen is None or episode_key(p) in set(unseen)]
    if not eps:
        log.warning("none of the %d held-out episodes is held out by world simulator %s (different split): "
                    "imagined evaluation skipped", len(held_eps), ckpt)
        return None
    if unseen is None:
        log.warning("world simulator %s does not list its held-out episodes: some imagined episodes may be ones it "
                    "trained on", ckpt)
    return eps, imagine(cfg, ckpt, eps)


def imagine(cfg, ckpt: str, eps: list) -> list[torch.Tensor]:
    """Open-loop replays of `eps` from their first frame and recorded actions by world simulator
    `ckpt`, batched per task: per episode (T+1, 3, H, W) uint8."""
    from worldenv_core.envs.imagined import ImaginedSimulator, replay_from_start

    out = {}
    g = torch.Generator().manual_seed(cfg.seed)
    for tid in sorted({ep.meta.task_id for ep in eps}):
        sim = ImaginedSimulator.from_checkpoint(ckpt, tid, cfg.imagined.sampling_steps,
                                                expect={"image_size": cfg.task.image_size, "chunk": cfg.task.chunk})
        group = [ep for ep in eps if ep.meta.task_id == tid]
        for ep, frames in zip(group, replay_from_start(sim, group, camera=cfg.camera, generator=g)):
            out[id(ep)] = frames
    log.info("imagined %d episodes with world simulator %s", len(eps), ckpt)
    return [out[id(ep)] for ep in eps]


def imagined_copies(cfg, ckpt: str, episodes: list) -> list:
    """The training episodes as the world simulator imagines them (it trained on them), with the
    real episodes' oracle flags as labels: so the reflector also learns what success looks like in
    the world model's rendering, which is where post-training asks it."""
    import dataclasses

    return [dataclasses.replace(ep, images={cfg.camera: frames.permute(0, 2, 3, 1).numpy()})
            for ep, frames in zip(episodes, imagine(cfg, ckpt, episodes))]


def evaluate_videos(model, encoder, episodes, videos, stride: int, eta: float) -> tuple[dict, list]:
    """Score every video at its chunk boundaries (and last frame) against the real episode's
    labels. Returns the report and the per-episode (steps, scores) curves."""
    steps_all, scores_all, labels_all, curves = [], [], [], []
    outcomes = defaultdict(list)  # source -> [StopOutcome]
    per_eta = {e: [] for e in ETA_SWEEP}
    for ep, video in zip(episodes, videos):
        steps = check_steps(len(video), stride)
        scores = prefix_scores(model, video, ep.meta.instruction, steps, encoder).numpy()
        labels = success_labels(ep.success)[steps]
        steps_all.append(steps), scores_all.append(scores), labels_all.append(labels)
        curves.append((steps, scores))
        ts = first_success(ep.success)
        for source in ("all", ep.meta.source):
            outcomes[source].append(StopOutcome(ts, first_stop(steps, scores, eta)))
        for e in ETA_SWEEP:
            per_eta[e].append(StopOutcome(ts, first_stop(steps, scores, e)))
    scores, labels = np.concatenate(scores_all), np.concatenate(labels_all)
    report = {"per_step": binary_metrics(scores, labels, eta),
              "termination": {src: termination_metrics(o) for src, o in outcomes.items()},
              "eta_sweep": {str(e): {"per_step_f1": binary_metrics(scores, labels, e)["f1"],
                                     "termination_f1": termination_metrics(o)["f1"]} for e, o in per_eta.items()}}
    return report, curves


def _headline(report: dict) -> dict:
    out = {}
    if "cross_validation" in report:
        v = report["cross_validation"]
        out.update(chosen_eta=v["chosen_eta"], real_termination_f1_at_chosen_eta=v["real_termination_at_chosen_eta"]["f1"])
    for kind in ("real", "imagined"):
        if kind in report:
            r = report[kind]
            out.update({f"{kind}_step_f1": r["per_step"]["f1"], f"{kind}_step_auroc": r["per_step"]["auroc"],
                        f"{kind}_step_accuracy": r["per_step"]["accuracy"],
                        f"{kind}_termination_f1": r["termination"]["all"]["f1"]})
    return out


def write_report(report: dict, curves: dict, held_eps, imagined_eps, cfg, work: Path) -> None:
    (work / "reflector_eval.json").write_text(json.dumps(report, indent=2))
    kinds = [k for k in ("real", "imagined") if k in report]
    md = [f"Reflector on {report['held_out_episodes']} held-out episodes (eta = {report['eta']}; scored every "
          f"{cfg.frame_stride} frames and at the last frame)", "",
          "| video | step accuracy | step F1 | step AUROC | term. precision | term. recall | term. F1 | "
          "false stop before success | false stop in failure | missed success | timing error (median steps) | episodes |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind in kinds:
        for src, t in report[kind]["termination"].items():
            p = report[kind]["per_step"] if src == "all" else None
            md.append(f"| {kind} ({src}) | " + (f"{p['accuracy']:.3f} | {p['f1']:.3f} | {p['auroc']:.3f}" if p else "| |")
                      + f" | {t['precision']:.3f} | {t['recall']:.3f} | {t['f1']:.3f} | {t['false_stop_before_success_rate']:.2f} | "
                      f"{t['false_stop_in_failure_rate']:.2f} | {t['missed_success_rate']:.2f} | {t['timing_error_median']:.1f} | "
                      f"{t['episodes']} |")
    md += ["", "Termination F1 by eta: | eta | " + " | ".join(kinds) + " |", "|---|" + "---|" * len(kinds)]
    md += [f"| {e} | " + " | ".join(f"{report[k]['eta_sweep'][str(e)]['termination_f1']:.3f}" for k in kinds) + " |"
           for e in ETA_SWEEP]
    if "cross_validation" in report:
        v, t = report["cross_validation"], report["cross_validation"]["real_termination_at_chosen_eta"]
        md += ["", f"eta chosen by {v['folds']}-fold cross-validation over the {v['episodes']} training episodes "
               f"(out-of-fold termination F1 by eta: " + ", ".join(f"{e} {m['termination_f1']:.3f}" for e, m in
                                                                 v["eta_sweep"].items()) + f"): {v['chosen_eta']}; "
               f"held-out real termination at it: precision {t['precision']:.3f}, recall {t['recall']:.3f}, "
               f"**F1 {t['f1']:.3f}** ({t['false_stops']} false stops, {t['missed_successes']} missed successes)"]
    (work / "reflector_eval.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    _plot_curves(curves, held_eps, imagined_eps, cfg, work / "reflector_curves.png")


def _plot_curves(curves: dict, held_eps, imagined_eps, cfg, path: Path) -> None:
    """R(t) of a few held-out episodes, real (solid) and imagined (dashed), with eta and t_success."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(cfg.plots, len(held_eps))
    fig, axes = plt.subplots(1, max(1, n), figsize=(3.2 * max(1, n), 2.8), squeeze=False)
    imagined_idx = {id(ep): i for i, ep in enumerate(imagined_eps)}
    for ax, i in zip(axes[0], range(n)):
        ep = held_eps[i]
        ax.plot(*curves["real"][i], label="real")
        if "imagined" in curves and id(ep) in imagined_idx:
            ax.plot(*curves["imagined"][imagined_idx[id(ep)]], "--", label="imagined")
        ax.axhline(cfg.eta, color="gray", lw=0.8)
        ts = first_success(ep.success)
        if ts is not None:
            ax.axvline(ts, color="green", lw=0.8)
        ax.set_ylim(-0.05, 1.05)
        ax.set_title(f"task {ep.meta.task_id} {ep.meta.source} {'ok' if ts is not None else 'fail'}", fontsize=8)
        ax.set_xlabel("step")
    if n:
        axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path.with_suffix(".tmp.png"))
    plt.close(fig)
    path.with_suffix(".tmp.png").replace(path)
