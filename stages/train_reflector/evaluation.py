"""train_reflector's evaluation and its section of the experiment report: the reflector on
held-out real episodes and on the world simulator's open-loop replays of the same episodes:
per-step accuracy / F1 / AUROC at eta, termination (correct stops, false stops, missed
successes, timing error), the eta sweep, and R(t) plots."""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from stages.train_reflector.horizon import lead_table, plot_by_lead, recognition_by_lead
from worldenv_core.contract import TaskContract
from worldenv_core.data.selection import episode_key
from worldenv_core.imagination.simulator import ImaginedSimulator, rendered_copy, replay_from_start
from worldenv_core.manifest import ArtefactError
from worldenv_core.stats import binary_metrics
from worldenv_core.models.checkpoint import read_config
from worldenv_core.report import ReportContext, markdown_table, short_run, titled
from worldenv_core.rl.termination import (StopOutcome, check_steps, first_stop, first_success, success_labels,
                                          termination_metrics)
from worldenv_core.stage import resolve_checkpoint
from worldenv_core.viz import figure, save_figure

log = logging.getLogger("worldenv.train_reflector")
ETA_SWEEP = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


# the held-out videos scored: as recorded, as the world model draws those frames, as it imagines them
KINDS = ("real", "rendered", "imagined")


def termination_at(episodes, curves, eta: float) -> dict:
    """Termination metrics of already scored (steps, R) curves at another eta."""
    return termination_metrics([StopOutcome(first_success(ep.success), first_stop(steps, scores, eta))
                                for ep, (steps, scores) in zip(episodes, curves)])


def imagine_held_out(cfg, contract: TaskContract, stage, held: list[Path], held_eps):
    """World-simulator replays of the held-out episodes the world model did not train on, or None
    when the experiment has no world simulator yet. `imagined.worldsim_from`: a train_worldsim
    record id or checkpoint folder; null = the latest of this task and scale."""
    ref = cfg.imagined.worldsim_from
    try:
        ckpt = resolve_checkpoint(stage, ref, "train_worldsim", contract.name, cfg.scale.name)
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
    return eps, ckpt


def simulators(cfg, contract: TaskContract, ckpt: str, eps: list) -> dict:
    """World simulator `ckpt` set up for each task of `eps`: task id -> ImaginedSimulator."""
    return {tid: ImaginedSimulator.from_checkpoint(ckpt, tid, cfg.imagined.sampling_steps, contract=contract)
            for tid in sorted({ep.meta.task_id for ep in eps})}


def imagine(cfg, sims: dict, eps: list) -> list[torch.Tensor]:
    """Open-loop replays of `eps` from their first frame and recorded actions by the world simulator
    set up per task in `sims` (`simulators`), batched per task: per episode (T+1, 3, H, W) uint8."""
    out = {}
    g = torch.Generator().manual_seed(cfg.seed)
    for tid, sim in sims.items():
        group = [ep for ep in eps if ep.meta.task_id == tid]
        for ep, frames in zip(group, replay_from_start(sim, group, camera=cfg.camera, generator=g)):
            out[id(ep)] = frames
    log.info("imagined %d episodes of %d tasks", len(eps), len(sims))
    return [out[id(ep)] for ep in eps]


def evaluate_videos(model, encoder, episodes, videos, stride: int, eta: float) -> tuple[dict, list]:
    """Score every video at its chunk boundaries (and last frame) against the real episode's
    labels. Returns the report and the per-episode (steps, scores) curves."""
    steps_all, scores_all, labels_all, curves = [], [], [], []
    outcomes = defaultdict(list)  # source -> [StopOutcome]
    per_eta = {e: [] for e in ETA_SWEEP}
    for ep, video in zip(episodes, videos):
        steps = check_steps(len(video), stride)
        scores = model.score_prefixes(video, ep.meta.instruction, steps, encoder).numpy()
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


def evaluate_held_out(cfg, contract: TaskContract, stage, model, encoder, held: list[Path], held_eps: list,
                      cv: dict | None, work: Path) -> dict:
    """The reflector on the held-out real videos and (when the experiment has a world simulator) on
    its replays of them; writes reflector_eval.{json,md} and reflector_curves.png into `work`."""
    videos = {"real": [ep.video(cfg.camera) for ep in held_eps]}
    imagined_eps, by_lead = held_eps, None
    if cfg.imagined.enabled:
        imagined = imagine_held_out(cfg, contract, stage, held, held_eps)
        if imagined is not None:
            imagined_eps, ckpt = imagined
            sims = simulators(cfg, contract, ckpt, imagined_eps)  # loaded once, for all three uses below
            videos["imagined"] = imagine(cfg, sims, imagined_eps)
            # the real frames as the world model draws them: what its rendering alone costs the verdict
            videos["rendered"] = [rendered_copy(sims[ep.meta.task_id], ep.video(cfg.camera)) for ep in imagined_eps]
            if cfg.imagined.leads:  # and from a few steps before each outcome: where the verdict is lost
                by_lead = recognition_by_lead(model, encoder, sims, imagined_eps, cfg.eta, cfg.frame_stride,
                                              cfg.camera, cfg.imagined.leads,
                                              generator=torch.Generator().manual_seed(cfg.seed))
                plot_by_lead(by_lead, work / "reflector_by_lead.png")
    report = {"eta": float(cfg.eta), "held_out_episodes": len(held_eps)}
    if by_lead is not None:
        report["imagined_by_lead"] = by_lead
    curves = {}
    for kind, vids in videos.items():
        eps = held_eps if kind == "real" else imagined_eps
        report[kind], curves[kind] = evaluate_videos(model, encoder, eps, vids, cfg.frame_stride, cfg.eta)
    if cv is not None:  # the held-out episodes chose nothing: judged at the chosen eta off their curves
        cv["real_termination_at_chosen_eta"] = termination_at(held_eps, curves["real"], cv["chosen_eta"])
        report["cross_validation"] = cv
    write_evaluation(report, cfg.frame_stride, work)
    _plot_curves(curves, held_eps, imagined_eps, cfg.plots, cfg.eta, work / "reflector_curves.png")
    return report


def headline(report: dict) -> dict:
    out = {}
    if "cross_validation" in report:
        v = report["cross_validation"]
        out.update(chosen_eta=v["chosen_eta"], real_termination_f1_at_chosen_eta=v["real_termination_at_chosen_eta"]["f1"])
    for kind in KINDS:
        if kind in report:
            r = report[kind]
            out.update({f"{kind}_step_f1": r["per_step"]["f1"], f"{kind}_step_auroc": r["per_step"]["auroc"],
                        f"{kind}_step_accuracy": r["per_step"]["accuracy"],
                        f"{kind}_termination_f1": r["termination"]["all"]["f1"]})
    for lead, r in report.get("imagined_by_lead", {}).get("leads", {}).items():  # the share recognised per lead
        if r["successes"]:
            out[f"imagined_recognised_from_{lead}_before"] = round(r["recognised"] / r["successes"], 3)
    return out


def write_evaluation(report: dict, frame_stride: int, work: Path) -> None:
    (work / "reflector_eval.json").write_text(json.dumps(report, indent=2))
    kinds = [k for k in KINDS if k in report]
    rows = []
    for kind in kinds:
        for src, t in report[kind]["termination"].items():
            p = report[kind]["per_step"] if src == "all" else None
            rows.append([f"{kind} ({src})", *([f"{p['accuracy']:.3f}", f"{p['f1']:.3f}", f"{p['auroc']:.3f}"] if p else ["", "", ""]),
                         f"{t['precision']:.3f}", f"{t['recall']:.3f}", f"{t['f1']:.3f}",
                         f"{t['false_stop_before_success_rate']:.2f}", f"{t['false_stop_in_failure_rate']:.2f}",
                         f"{t['missed_success_rate']:.2f}", f"{t['timing_error_median']:.1f}", t["episodes"]])
    md = [f"Reflector on {report['held_out_episodes']} held-out episodes (eta = {report['eta']}; scored every "
          f"{frame_stride} frames and at the last frame)", "",
          *markdown_table(["video", "step accuracy", "step F1", "step AUROC", "term. precision", "term. recall",
                           "term. F1", "false stop before success", "false stop in failure", "missed success",
                           "timing error (median steps)", "episodes"], rows),
          "", "Termination F1 by eta:", "",
          *markdown_table(["eta", *kinds], [[e, *(f"{report[k]['eta_sweep'][str(e)]['termination_f1']:.3f}" for k in kinds)]
                                            for e in ETA_SWEEP])]
    if "cross_validation" in report:
        v, t = report["cross_validation"], report["cross_validation"]["real_termination_at_chosen_eta"]
        md += ["", f"eta chosen by {v['folds']}-fold cross-validation over the {v['episodes']} training episodes "
               f"(out-of-fold termination F1 by eta: " + ", ".join(f"{e} {m['termination_f1']:.3f}" for e, m in
                                                                 v["eta_sweep"].items()) + f"): {v['chosen_eta']}; "
               f"held-out real termination at it: precision {t['precision']:.3f}, recall {t['recall']:.3f}, "
               f"**F1 {t['f1']:.3f}** ({t['false_stops']} false stops, {t['missed_successes']} missed successes)"]
    if "imagined_by_lead" in report:
        md += ["", f"Imagined from a few steps before each held-out outcome (real frames up to there, then the "
               f"recorded actions open loop; scored up to {report['imagined_by_lead']['after']} steps past it):", "",
               *markdown_table(*lead_table(report["imagined_by_lead"]))]
    (work / "reflector_eval.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def _plot_curves(curves: dict, held_eps, imagined_eps, plots: int, eta: float, path: Path) -> None:
    """R(t) of a few held-out episodes, real (solid) and imagined (dashed), with eta and t_success."""
    n = min(plots, len(held_eps))
    fig, axes = figure(1, max(1, n), figsize=(3.2 * max(1, n), 2.8), squeeze=False)
    imagined_idx = {id(ep): i for i, ep in enumerate(imagined_eps)}
    for ax, i in zip(axes[0], range(n)):
        ep = held_eps[i]
        ax.plot(*curves["real"][i], label="real")
        if "imagined" in curves and id(ep) in imagined_idx:
            ax.plot(*curves["imagined"][imagined_idx[id(ep)]], "--", label="imagined")
        ax.axhline(eta, color="gray", lw=0.8)
        ts = first_success(ep.success)
        if ts is not None:
            ax.axvline(ts, color="green", lw=0.8)
        ax.set_ylim(-0.05, 1.05)
        ax.set_title(f"task {ep.meta.task_id} {ep.meta.source} {'ok' if ts is not None else 'fail'}", fontsize=8)
        ax.set_xlabel("step")
    if n:
        axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def section(ctx: ReportContext, limit: int = 4) -> list[str]:
    """Every recent reflector, newest first, not only the newest: evaluations and post-training
    name the one they used. How each was trained comes from its record's tags and metrics."""
    rows = []
    for r in reversed(ctx.find("train_reflector")[-limit:]):
        acc = ctx.report_json(r, "reflector_eval.json")
        if not acc:
            continue
        ckpt = r.files("checkpoint")
        run = f"`{r.id}` ({short_run(str(Path(ckpt[0].path).parent))})" if ckpt else f"`{r.id}`"  # as evaluations name it
        training = r.metrics.get("training", "")
        for kind in KINDS:
            if kind in acc:
                p, t = acc[kind]["per_step"], acc[kind]["termination"]["all"]
                rows.append([run, r.tags.get("data"), r.tags.get("reward", "trained head"), training, acc["eta"],
                             acc["held_out_episodes"], kind, f"{p['accuracy']:.3f}", f"{p['f1']:.3f}",
                             f"{p['auroc']:.3f}", f"{t['f1']:.3f}"])
        if "cross_validation" in acc:  # the eta the checkpoint carries, chosen without the held-out episodes
            cv = acc["cross_validation"]
            rows.append([run, r.tags.get("data"), r.tags.get("reward", "trained head"), training,
                         f"{cv['chosen_eta']} ({cv['folds']}-fold CV)", acc["held_out_episodes"], "real", "", "", "",
                         f"{cv['real_termination_at_chosen_eta']['f1']:.3f}"])
    return titled("Reflector (held-out episodes, newest first)", markdown_table(
        ["record", "data", "reward", "training", "eta", "held out", "video", "step accuracy", "step F1", "step AUROC",
         "termination F1"], rows) if rows else [])
