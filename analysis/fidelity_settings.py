"""Re-measure a trained world simulator's open-loop fidelity with other render settings.

    python -m analysis.fidelity_settings outputs/libero_goal-small [--record ID] [--model FOLDER]
        [--detail-gate 0 0.1 0.3] [--sampling-steps 1 2] [--noise-scale 1 0] [--static-snap 0 0.2]
        [--horizons 8 16 32 64 128]

Reads the train_worldsim record (default: the newest), its checkpoint (or `--model`, a checkpoint
folder trained on from it elsewhere, e.g. from a latent pack on a GPU host) and the held-out episodes of that
checkpoint, and prints PSNR / SSIM beside copy-the-last-frame for every
combination of detail gate, sampling steps, sampler temperature and static snap: the sweep
behind the defaults `detail_gate`, `noise_scale` and `static_snap`.
Nothing is trained and nothing is written.

A released checkpoint (no train_worldsim record on this machine): `--model checkpoints/<suite>/worldsim --data
data/<suite>` measures it on the held-out episodes its meta names, as far as they are under `--data` (the
expert demos come back with `collect`'s command; the others are skipped and counted), with the task's
`train_worldsim` settings (`scale=small`). The gripper's region (its projected disc, `gripper_mask`) is scored
apart: where the robot turns into a smear, the whole frame's SSIM hides it.

    python -m analysis.fidelity_settings --model checkpoints/libero_spatial/worldsim --data data/libero_spatial \
        --horizons 8 16 32 64
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

from omegaconf import OmegaConf

from stages.train_worldsim.evaluation import fidelity_by_horizon
from worldenv_core.cli import user_errors
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.errors import ConfigError
from worldenv_core.data.selection import episode_key, holdout_split
from worldenv_core.envs.scene_geometry import scenes_file, task_scenes
from worldenv_core.kinematics.arm import SerialArm
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import NextStateModel
from worldenv_core.manifest import Manifest
from worldenv_core.stage import task_contract
from worldenv_core.models.checkpoint import load_model


def main(argv: list[str] | None = None) -> list[dict]:

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("experiment_dir", nargs="?", help="with a train_worldsim record (not needed with --data)")
    ap.add_argument("--record", help="a train_worldsim record id (default: the newest)")
    ap.add_argument("--detail-gate", type=float, nargs="+", default=[None], help="default: the checkpoint's")
    ap.add_argument("--sampling-steps", type=int, nargs="+", default=[None], help="default: the checkpoint's")
    ap.add_argument("--noise-scale", type=float, nargs="+", default=[None], help="default: the checkpoint's")
    ap.add_argument("--static-snap", type=float, nargs="+", default=[None], help="default: the checkpoint's")
    ap.add_argument("--model", help="a checkpoint folder to measure instead of the record's (same held-out episodes)")
    ap.add_argument("--horizons", type=int, nargs="+", help="default: the record's fidelity.horizons")
    ap.add_argument("--data", help="a released --model's task data folder (data/<suite>): its held-out episodes there")
    args = ap.parse_args(argv)
    with user_errors():
        if args.data:
            cfg, model, meta, held = released(args.model, args.data)
        else:
            if not args.experiment_dir:
                raise ConfigError("name an experiment directory with a train_worldsim record, or --model and --data")
            cfg, model, meta, held = recorded(args.experiment_dir, args.record, args.model)
    if args.horizons:
        cfg.fidelity.horizons = args.horizons
    held_eps = [read_episode(p, cameras=[cfg.camera]) for p in held]
    kinematics = NextStateModel(**meta["kinematics"])
    cameras = {int(t): PinholeCamera.from_dict(c) for t, c in meta["cameras"].items()}
    arms = {int(t): SerialArm.from_dict(a) for t, a in (meta.get("arms") or {}).items()}
    if set(arms) != set(cameras):  # a model saved before arms were kept: its scenes' arms, for the arm's region
        cache = scenes_file(cfg.experiment_dir) if cfg.get("experiment_dir") else None
        arms = task_scenes(task_contract(cfg), cfg.camera, sorted(cameras), cache)[1]
    print(f"{args.model or args.record or 'the newest train_worldsim'}: {len(held_eps)} held-out episodes, "
          f"{cfg.fidelity.starts_per_episode} starts each\n")
    print("| detail gate | sampling steps | noise scale | static snap | horizon | PSNR model | PSNR copy-last | "
          "SSIM model | SSIM copy-last | SSIM static: model / copy | SSIM moving: model / copy | "
          "SSIM gripper: model / copy | PSNR gripper: model / copy | SSIM arm: model / copy |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    defaults = model.sampling_steps, model.noise_scale, model.static_snap
    for gate, steps, noise, snap in itertools.product(args.detail_gate, args.sampling_steps, args.noise_scale,
                                                      args.static_snap):
        gate = model.detail_gate if gate is None else gate
        model.sampling_steps = steps or defaults[0]
        model.noise_scale = defaults[1] if noise is None else noise
        model.static_snap = defaults[2] if snap is None else snap
        fidelity, _ = fidelity_by_horizon(cfg, model, kinematics, cameras, held_eps, gate, arms)
        for h, v in fidelity.items():
            rows.append({"detail_gate": gate, "sampling_steps": model.sampling_steps, "noise_scale": model.noise_scale,
                         "static_snap": model.static_snap, "horizon": h, **v})
            print(f"| {gate:g} | {model.sampling_steps} | {model.noise_scale:g} | {model.static_snap:g} | {h} | "
                  f"{v['model_psnr']:.2f} | {v['copy_psnr']:.2f} | {v['model_ssim']:.3f} | {v['copy_ssim']:.3f} | "
                  f"{v['model_ssim_static']:.3f} / {v['copy_ssim_static']:.3f} | "
                  f"{v['model_ssim_moving']:.3f} / {v['copy_ssim_moving']:.3f} | "
                  f"{v.get('model_ssim_gripper', float('nan')):.3f} / {v.get('copy_ssim_gripper', float('nan')):.3f} | "
                  f"{v.get('model_psnr_gripper', float('nan')):.2f} / {v.get('copy_psnr_gripper', float('nan')):.2f} | "
                  f"{v.get('model_ssim_arm', float('nan')):.3f} / {v.get('copy_ssim_arm', float('nan')):.3f} |",
                  flush=True)
    return rows


def recorded(experiment_dir: str, record_id: str | None, model_dir: str | None):
    """The train_worldsim record's config, its checkpoint (or `model_dir`) and held-out episodes."""
    manifest = Manifest(experiment_dir)
    record = manifest.get(record_id) if record_id else manifest.latest("train_worldsim")
    cfg = OmegaConf.create(record.config)
    model, config = load_model(model_dir or manifest.resolve(record, kind="checkpoint")[0].parent)
    meta = config["meta"]
    paths = [p for rid in record.inputs for p in manifest.resolve(manifest.get(rid), kind="episodes")]
    if "held_out" in meta:  # the checkpoint's own split (a model trained on from another keeps its start's)
        keys = set(meta["held_out"])
        held = [p for p in paths if episode_key(p) in keys]
    else:
        _, held = holdout_split(paths, cfg.holdout_every)
    return cfg, model, meta, held


def released(model_dir: str | None, data: str):
    """A checkpoint outside any manifest: the task's train_worldsim settings and the held-out episodes its meta
    names that are under `data` (keys are relative to the task's data folder)."""
    from worldenv_core.stage import compose_config

    if not model_dir:
        raise ConfigError("--data measures a released checkpoint: name it with --model")
    if not (Path(model_dir) / "model.safetensors").exists():
        raise ConfigError(f"--model {model_dir}: no model.safetensors there (a checkpoint folder is needed)")
    model, config = load_model(model_dir)
    meta = config["meta"]
    if not meta.get("held_out"):
        raise ConfigError(f"--model {model_dir}: its meta names no held-out episodes")
    present = [Path(data) / k for k in meta["held_out"] if (Path(data) / k).exists()]
    if not present:
        raise ConfigError(f"--data {data}: none of the {len(meta['held_out'])} held-out episodes of {model_dir} are "
                          f"there (e.g. {meta['held_out'][0]})")
    print(f"{len(present)} of {len(meta['held_out'])} held-out episodes found under {data}")
    cfg = compose_config("train_worldsim", [f"+task={meta['task']}", "scale=small"])
    cfg.camera = meta["camera"]
    return cfg, model, meta, present


if __name__ == "__main__":
    main()
