"""Open-loop training (phase 3 of `train_worldsim`) from a latent pack, on a machine with a GPU and
neither the episodes nor the simulator. The same phase, Trainer and resumable checkpoints as
`train_worldsim init_from=...`; the result is a checkpoint folder that every stage takes
(`worldsim_from=`), its meta saying how it was trained. Settings are train_worldsim's (its config
and scale), overridden as `key=value`.

    python -m stages.train_worldsim.latent_pack <model> '<episodes>' --out pack.safetensors   # here
    python -m stages.train_worldsim.from_pack pack.safetensors <model> --work w --minutes 6 \\
        --snapshots 3 rollout.chunks=8 rollout.batch_size=64                                   # there

`--minutes` sizes the run from a timing of a few steps on a copy of the model (recorded in the work
dir, so a re-run resumes to the same total) and stops it, saved, at the first step past that many
minutes if the plan runs over; `--snapshots K` also saves the EMA model at K-1 equal
fractions of the run (`snapshot_<step>/`), a compute curve from one run.

The world model's model-size and data curves: `--width W` trains a *fresh* flow network of width W on
the same autoencoder (its latent scales and kinematics kept, so the pack still serves it; start it with
`rollout.chunks=0`, teacher forcing, then go on open loop from its result), and `--every N` trains on
every N-th episode of the pack only.
"""

from __future__ import annotations

import argparse
import copy
import logging
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from stages.train_worldsim.latent_pack import pack_chunks, read_pack
from stages.train_worldsim.training import rollout_phase
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.models.checkpoint import load_checkpoint, read_config, save_model
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device, planned_steps, planned_total

log = logging.getLogger("worldenv.train_worldsim.from_pack")
CONF = Path(__file__).resolve().parents[2] / "conf"


def settings(overrides: list[str]):
    """train_worldsim's own config (with its scale), so both entry points train alike."""
    base = OmegaConf.load(CONF / "train_worldsim.yaml")
    scale = OmegaConf.load(CONF / "scale" / "small.yaml")
    logger = OmegaConf.load(CONF / "logger" / "tensorboard.yaml")
    for key in ("defaults", "hydra"):
        base.pop(key, None)
    cfg = OmegaConf.merge({"scale": scale, "logger": logger}, base, OmegaConf.from_dotlist(overrides))
    return cfg


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pack")
    p.add_argument("model", help="the world model checkpoint folder the pack was made from")
    p.add_argument("--work", required=True, help="work dir: resumable checkpoints, curves, the result")
    how_long = p.add_mutually_exclusive_group(required=True)
    how_long.add_argument("--steps", type=int)
    how_long.add_argument("--minutes", type=float, help="train for about this long: planned from timed steps, and saved and stopped at the "
                          "deadline if the plan runs over (a re-run goes on)")
    p.add_argument("--snapshots", type=int, default=1, help="K: save the EMA model at K equal fractions of the run")
    p.add_argument("--width", type=int, help="a fresh flow network of this width on the model's autoencoder")
    p.add_argument("--every", type=int, default=1, help="N: train on every N-th episode of the pack")
    p.add_argument("overrides", nargs="*", help="train_worldsim settings, key=value")
    args = p.parse_intermixed_args(argv)
    deadline = time.monotonic() + 60 * args.minutes if args.minutes else None  # this sitting's wall clock
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    cfg = settings(args.overrides)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    device = pick_device(cfg.device)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True

    if args.every < 1 or (args.width is not None and args.width < 8):
        raise SystemExit(f"--every must be >= 1 (got {args.every}) and --width >= 8 (got {args.width})")
    base, base_meta = load_checkpoint(args.model, "worldsim")
    latents, episodes, pack_meta = read_pack(args.pack, args.model)
    latents, episodes = latents[::args.every], episodes[::args.every]
    cameras = {int(t): PinholeCamera.from_dict(c) for t, c in base_meta["cameras"].items()}
    model_cfg = read_config(args.model)["model"]
    fresh = args.width is not None  # a new flow network: its steps start from zero, from no earlier step
    if fresh:
        model_cfg, base = fresh_velocity(base, model_cfg, args.width, cfg.seed)
    model = copy.deepcopy(base).to(device)
    ema = copy.deepcopy(model).requires_grad_(False)
    optimizer = torch.optim.AdamW(model.velocity.parameters(), lr=cfg.flow.lr)
    chunks_of = lambda ahead: pack_chunks(latents, episodes, model, ahead)  # noqa: E731 (its chunk and memory offsets only)

    def time_steps(seconds: float) -> int:  # on copies, so the run itself starts from the untouched model
        probe_model, probe_ema = copy.deepcopy(model), copy.deepcopy(ema)
        probe_opt = torch.optim.AdamW(probe_model.velocity.parameters(), lr=cfg.flow.lr)
        probe = rollout_phase(probe_model, probe_ema, probe_opt, chunks_of, cameras, cfg, device)
        return planned_steps(probe.step, iter(probe.batches(0)), seconds)

    steps = planned_total(work, args.steps, args.minutes, time_steps, args.overrides)
    cfg.rollout.steps = steps

    prior = 0 if fresh else int(base_meta.get("rollout_steps") or 0)
    meta = {**base_meta, "rollout_steps": prior + steps, "init_from_step": None if fresh else base_meta.get("step"),
            "rollout_chunks": int(cfg.rollout.chunks), "rollout_batch_size": int(cfg.rollout.batch_size),
            "trained_from": {"latent_pack": pack_meta["encoder_sha256"][:12], "episodes": len(episodes),
                             "fresh_width": args.width, "every": args.every,
                             "device": torch.cuda.get_device_name() if device.type == "cuda" else str(device)}}
    trainer = Trainer(work, model, {"flow": optimizer}, model_config=model_cfg, meta=meta, desc="open-loop (pack)",
                      log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                      extra_state=lambda: {"ema": ema.state_dict()},
                      tracker=make_tracker(cfg.logger, work, "train_worldsim", base_meta["task"], {}),
                      precision=cfg.precision)
    if "ema" in trainer.extra:
        ema.load_state_dict(trainer.extra["ema"])
    marks = {round(steps * k / args.snapshots) for k in range(1, args.snapshots)}

    def snapshot(done: int) -> None:
        if done in marks:
            save_model(work / f"snapshot_{done}", copy.deepcopy(ema).cpu(), model_cfg,
                       {**meta, "rollout_steps": prior + done, "step": done})

    log.info("open-loop training from %s: %d episodes, %d steps (%s), chunks %d, batch %d, on %s", args.pack,
             len(episodes), steps, f"{args.minutes} min planned" if args.minutes else "given", cfg.rollout.chunks,
             cfg.rollout.batch_size, device)
    trainer.fit([rollout_phase(model, ema, optimizer, chunks_of, cameras, cfg, device)], after_step=snapshot,
                deadline=deadline)
    final = trainer.save_final(work / "worldsim", model=ema, rollout_steps=prior + trainer.step)
    trainer.close_off("losses.png", f"train_worldsim from a latent pack {base_meta['task']}")
    log.info("saved %s (%d of %d steps%s, %.0f s this sitting)", final, trainer.step, steps,
             "; the deadline came first, a re-run goes on" if trainer.stopped_early else "", trainer.wall_s)
    return final


def fresh_velocity(base, model_cfg: dict, width: int, seed: int):
    """-> (config, model): `base` with a newly initialised flow network of `width`; the autoencoder and the
    latent and delta scales are base's (the flow works in its latent space, which the pack holds)."""
    from hydra.utils import instantiate

    cfg = {**model_cfg, "width": int(width)}
    torch.manual_seed(seed)
    model = instantiate(cfg, _convert_="all")
    kept = {k: v for k, v in base.state_dict().items() if not k.startswith("velocity.")}
    missing, unexpected = model.load_state_dict(kept, strict=False)
    assert not unexpected and all(k.startswith("velocity.") for k in missing), (missing, unexpected)
    return cfg, model


if __name__ == "__main__":
    main()
