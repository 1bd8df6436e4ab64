"""How the reflector is trained: BCE on balanced prefixes through the shared Trainer, with hard
negatives mined from the model's own near misses, and eta chosen by K-fold cross-validation
over the training episodes (each fold a reflector of its own, resumable)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tqdm import tqdm

from stages.train_reflector.evaluation import ETA_SWEEP, evaluate_videos, imagine, simulators, termination_at
from worldenv_core.contract import TaskContract
from worldenv_core.data.selection import episode_key
from worldenv_core.models.reflector_data import PrefixSampler
from worldenv_core.rl.termination import best_eta
from worldenv_core.stage import ConfigError
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Phase, Trainer, optimize, per_step, random_shift, step_seed, trainer_options

log = logging.getLogger("worldenv.train_reflector")


def fit(cfg, contract: TaskContract, episodes: list, work: Path, device, encoder, meta_extra: dict, overall=None,
        worldsim: str | None = None):
    """Train (or resume, or find finished in `work`) a reflector on `episodes`; `overall`: a
    progress bar over several fits (the cross-validation's) that this one's steps advance;
    `worldsim`: the world model whose autoencoder a `worldsim_latent` frame encoder sees through.
    -> (model on the CPU in eval mode, its config, its meta, the loss history; [] when untrainable)."""
    try:
        sampler = PrefixSampler(episodes, cfg.camera, cfg.frame_stride, cfg.reflector.max_frames,
                                cfg.train.hard_negative_fraction, cfg.train.hard_window, cfg.train.label_delay)
    except ValueError as e:
        raise ConfigError(f"{e}; collect more episodes (policy rollouts give failures)") from None
    model_cfg = OmegaConf.to_container(cfg.reflector, resolve=True)
    model = instantiate(model_cfg, _convert_="all")
    if hasattr(getattr(model, "frame_encoder", None), "load_autoencoder"):  # a reward model may have no frame encoder
        model.frame_encoder.load_autoencoder(worldsim)
    model = model.to(device)
    meta = {"kind": "reflector", **contract.meta(), "camera": cfg.camera, "frame_stride": cfg.frame_stride,
            "eta": float(cfg.eta), "label_delay": cfg.train.label_delay, "episodes": len(episodes), **meta_extra,
            **sampler.counts()}
    history = []
    if any(p.requires_grad for p in model.parameters()):
        log.info("training on %d episodes (%s) for %d steps on %s; work dir %s", len(episodes), sampler.counts(),
                 cfg.train.steps, device, work)
        history = train(cfg, model, model_cfg, meta, sampler, encoder, work, device, overall)
    else:  # the VLM yes/no mode: nothing to train, its checkpoint is the config naming the VLM
        log.info("%s has nothing to train", type(model).__name__)
    return model.cpu().eval(), model_cfg, meta, history


def train(cfg, model, model_cfg: dict, meta: dict, sampler: PrefixSampler, encoder, work: Path, device,
          overall=None) -> list[dict]:
    """BCE on balanced prefixes; resumes from the work dir's last checkpoint. Returns the history."""
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.train.lr,
                            weight_decay=cfg.train.weight_decay)
    trainer = Trainer(work, model, {"reflector": opt}, model_config=model_cfg, meta=meta, desc="train_reflector",
                      log_every=cfg.train.log_every, checkpoint_every=cfg.train.checkpoint_every, overall=overall,
                      tracker=make_tracker(cfg.get("logger"), work, "train_reflector", meta["task"]),
                      **trainer_options(cfg, "train.batch_size"))
    total, mine_every = cfg.train.steps, cfg.train.mine.every
    if mine_every and mine_every <= trainer.step < total:  # resumed: the hard set the run had (checkpoints fall on mining steps)
        _mine(cfg, model, sampler, encoder, device, trainer.step - trainer.step % mine_every)

    def draw(step: int) -> dict:  # by step: resumes exactly
        return {**sampler.batch(cfg.train.batch_size, seed=step_seed(cfg.seed, step)),
                "shift_generator": torch.Generator().manual_seed(step_seed(cfg.seed, step, stream=7_000_003))}

    def step(b: dict) -> dict:
        frames, mask = _augment(model, b["frames"], b["mask"], cfg.train.augment_shift, b["shift_generator"])
        logits = model(frames.to(device), mask.to(device), encoder(b["instruction"]).to(device))
        label = b["label"].to(device)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, label)
        optimize(loss, opt, clip=1.0, params=list(model.parameters()))
        return {"bce": loss.item(), "batch_accuracy": ((logits > 0).float() == label).float().mean().item()}

    def after_step(done: int) -> None:
        if mine_every and done % mine_every == 0 and done < total:
            _mine(cfg, model, sampler, encoder, device, done)

    trainer.fit([Phase("bce", total, lambda start: per_step(draw, start), step)], after_step=after_step)
    meta["ranks"] = trainer.ranks  # data-parallel ranks it trained on (torchrun), in its checkpoint and record
    trainer.tracker.close()
    return trainer.history


def _mine(cfg, model, sampler: PrefixSampler, encoder, device, step: int) -> None:
    """Score every training episode's negative chunk boundaries with the current model and make
    the high-scoring ones (near misses) hard negatives until the next mining."""
    model.eval()
    lang = encoder(sampler.instructions).to(device)
    mined = sampler.mine(lambda i, frames, steps: model.score_prefixes(frames.to(device), lang[i], steps).cpu(),
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


def cross_validation_folds(paths: list[Path], folds: int) -> list[list[int]]:
    """K folds of the training episodes (indices), every K-th in sorted path order, so each fold
    mixes tasks and sources like the whole; a fold must leave something to train on."""
    if folds > len(paths) or folds < 2:
        raise ConfigError(f"eta_folds={folds} needs 2 <= folds <= the {len(paths)} training episodes "
                          f"(eta_folds=0 keeps the configured eta)")
    order = sorted(range(len(paths)), key=lambda i: paths[i])
    return [order[k::folds] for k in range(folds)]


def cross_validate_eta(cfg, contract: TaskContract, paths: list[Path], episodes: list, work: Path, device, encoder,
                       dreamed: list | None = None, worldsim: str | None = None) -> dict:
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
        model, *_ = fit(cfg, contract, fit_eps, work / "folds" / f"{k + 1}-of-{len(folds)}", device, encoder,
                        {"held_out": [episode_key(paths[i]) for i in fold]}, overall, worldsim)
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


def imagined_copies(cfg, contract: TaskContract, ckpt: str, episodes: list) -> list:
    """The training episodes as the world simulator imagines them (it trained on them), with the
    real episodes' oracle flags as labels: so the reflector also learns what success looks like in
    the world model's rendering, which is where post-training asks it."""
    return [dataclasses.replace(ep, images={cfg.camera: frames.permute(0, 2, 3, 1).numpy()})
            for ep, frames in zip(episodes, imagine(cfg, simulators(cfg, contract, ckpt, episodes), episodes))]


