"""train_worldsim's evaluation: open-loop fidelity on held-out episodes (PSNR / SSIM per horizon
beside copy-the-last-frame, with the plain decoding and the kinematic model's error), side-by-side
videos, held-out replays as MCAP, and the stage's section of the experiment report."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import torch

from worldenv_core.data.mcap_io import write_imagined_episode
from worldenv_core.imagination.simulator import ImaginedSimulator, open_loop_fidelity, replay_from_start
from worldenv_core.kinematics.next_state import state_errors
from worldenv_core.report import ReportContext, markdown_table, titled
from worldenv_core.imagination.recording import imagined_replay
from worldenv_core.viz import montage_video


def fidelity_by_horizon(cfg, model, kinematics, cameras, held_eps, detail_gate: float, arms=None) -> tuple[dict, list]:
    """horizon -> metrics averaged over all starts of all held-out tasks; side-by-side videos. `arms`: task id ->
    `SerialArm`, for a model whose maps draw the arm."""
    by_task = defaultdict(list)
    for ep in held_eps:
        by_task[ep.meta.task_id].append(ep)
    per_task, videos = [], []
    g = torch.Generator().manual_seed(cfg.seed)
    for tid, eps in sorted(by_task.items()):
        sim = ImaginedSimulator(model, kinematics, cameras[tid], detail_gate=detail_gate, arm=(arms or {}).get(tid))
        out = open_loop_fidelity(sim, eps, tuple(cfg.fidelity.horizons), cfg.fidelity.starts_per_episode,
                                 camera=cfg.camera, generator=g)
        per_task.append(out["horizons"])
        videos += out["videos"]
    fidelity = {}
    for h in cfg.fidelity.horizons:
        parts = [r[h] for r in per_task if r[h]["n"]]
        n = sum(p["n"] for p in parts)
        if n:
            fidelity[h] = {k: _weighted_mean([(p[k], p["n"]) for p in parts]) for k in parts[0] if k != "n"} | {"n": n}
    return fidelity, videos


def write_replays(model, kinematics, cameras, episodes, out_dir: Path, extra: dict, seed: int, arms=None) -> list[Path]:
    """Held-out episodes replayed open loop by the world model from their first frame, each written
    as an imagined episode with the real one beside it under `/real` (Foxglove:
    foxglove/imagined_vs_real.json shows both)."""
    g = torch.Generator().manual_seed(seed + 1)  # its own noise: the fidelity figures stay as they were
    paths = []
    for i, ep in enumerate(episodes):
        sim = ImaginedSimulator(model, kinematics, cameras[ep.meta.task_id], arm=(arms or {}).get(ep.meta.task_id))
        (frames, proprio), = replay_from_start(sim, [ep], camera=ep.meta.cameras[0], generator=g, with_proprio=True)
        imagined = imagined_replay(ep, frames, proprio, extra)
        paths.append(write_imagined_episode(out_dir / f"heldout_{i:02d}_task{ep.meta.task_id:02d}.mcap", imagined,
                                            real=ep))
    return paths


def _weighted_mean(values_weights) -> float:
    """Mean over tasks weighted by their sample counts, skipping tasks without a value (nan: e.g.
    no moving region at that horizon)."""
    pairs = [(v, w) for v, w in values_weights if v == v]
    return sum(v * w for v, w in pairs) / sum(w for _, w in pairs) if pairs else float("nan")


def evaluate_fidelity(cfg, model, kinematics, cameras, held_eps, work: Path, baseline=None, arms=None) -> dict:
    """Open-loop fidelity on held-out episodes (model vs copy-last-frame) and kinematics error.
    With detail transfer on, the model's plain decoding is measured too (`plain_psnr/ssim`);
    `baseline` (the model a fine-tuning started from) is measured on the same starts
    (`start_psnr/ssim`)."""
    model.eval()
    fidelity, videos = fidelity_by_horizon(cfg, model, kinematics, cameras, held_eps, model.detail_gate, arms)
    extra = [("plain", model, 0.0)] if model.detail_gate > 0 else []
    extra += [("start", baseline, baseline.detail_gate)] if baseline is not None else []
    for name, other, gate in extra:
        theirs, _ = fidelity_by_horizon(cfg, other.eval(), kinematics, cameras, held_eps, gate, arms)
        for h, v in fidelity.items():
            v.update({f"{name}_{key}": theirs[h][f"model_{key}"] for key in
                      ("psnr", "ssim", "ssim_moving", "ssim_gripper", "psnr_gripper") if f"model_{key}" in theirs[h]})
    kin = {f"kinematics_{h}step": state_errors(kinematics, held_eps, h) for h in (1, cfg.task.chunk)}
    (work / "videos").mkdir(exist_ok=True)
    for i, (real, fake) in enumerate(videos[: cfg.fidelity.videos]):
        n = min(len(real), len(fake))
        side = torch.cat([real[:n], fake[:n]], dim=-1).permute(0, 2, 3, 1).numpy()
        montage_video([side], work / "videos" / f"real_vs_imagined_{i}.gif", max_frames=n)
    report = {"fidelity": {str(h): v for h, v in sorted(fidelity.items())}, **kin,
              "beats_copy_baseline": bool(fidelity) and all(v["model_psnr"] > v["copy_psnr"] for v in fidelity.values()),
              "beats_copy_baseline_ssim": bool(fidelity) and all(v["model_ssim"] > v["copy_ssim"] for v in fidelity.values())}
    (work / "fidelity.json").write_text(json.dumps(report, indent=2))
    fmt = lambda v, k: f"{v[k]:.3f}" if k in v else "-"  # noqa: E731 (a figure only some runs have)
    md = markdown_table(["horizon (steps)", "PSNR model", "PSNR copy-last", "SSIM model", "SSIM copy-last",
                         "PSNR / SSIM plain decoding", "PSNR / SSIM / SSIM moving: starting model",
                         "SSIM static: model / copy", "SSIM moving: model / copy", "moving share",
                         "gripper SSIM: model / copy / start", "gripper PSNR: model / copy / start", "n"],
                        [[h, f"{v['model_psnr']:.2f}", f"{v['copy_psnr']:.2f}", f"{v['model_ssim']:.3f}",
                          f"{v['copy_ssim']:.3f}", f"{fmt(v, 'plain_psnr')} / {fmt(v, 'plain_ssim')}",
                          f"{fmt(v, 'start_psnr')} / {fmt(v, 'start_ssim')} / {fmt(v, 'start_ssim_moving')}",
                          f"{v['model_ssim_static']:.3f} / {v['copy_ssim_static']:.3f}",
                          f"{v['model_ssim_moving']:.3f} / {v['copy_ssim_moving']:.3f}", f"{v['moving_fraction']:.2f}",
                          f"{fmt(v, 'model_ssim_gripper')} / {fmt(v, 'copy_ssim_gripper')} / {fmt(v, 'start_ssim_gripper')}",
                          f"{fmt(v, 'model_psnr_gripper')} / {fmt(v, 'copy_psnr_gripper')} / {fmt(v, 'start_psnr_gripper')}",
                          v["n"]] for h, v in sorted(fidelity.items())])
    md += ["", *markdown_table(["kinematics", "pos median (mm)", "pos p90 (mm)", "rot median (deg)", "gripper MAE"],
                               [[f"{v['horizon']} step(s)", f"{v['pos_mm_median']:.2f}", f"{v['pos_mm_p90']:.2f}",
                                 f"{v['rot_deg_median']:.2f}", f"{v['grip_mae']:.3f}"] for v in kin.values()])]
    (work / "fidelity.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return report


def section(ctx: ReportContext) -> list[str]:
    """The newest world model of each training set side by side (the "w/o extra data" ablation)."""
    rows = []
    for data in ("expert+policy", "expert"):
        found = ctx.find("train_worldsim", data=data)
        fid = ctx.report_json(found[-1], "fidelity.json") if found else None
        for h, v in (fid or {}).get("fidelity", {}).items():
            rows.append([data, h, f"{v['model_psnr']:.2f}", f"{v['copy_psnr']:.2f}", f"{v['model_ssim']:.3f}",
                         f"{v['copy_ssim']:.3f}", f"{v['plain_ssim']:.3f}" if "plain_ssim" in v else "-"])
    return titled("World simulator (open loop on held-out episodes)", markdown_table(
        ["data", "horizon", "PSNR model", "PSNR copy-last", "SSIM model", "SSIM copy-last", "SSIM plain decoding"],
        rows) if rows else [])
