"""evaluate_imagination's measurements and its section of the experiment report: one policy's
imagined rollouts paired with their real replays, the summary over policies, the plot of
imagined against real success, side-by-side GIFs, and the before/after table of runs."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stages.evaluate_imagination.contexts import PairedContext
from stages.evaluate_imagination.judges import Judge
from stages.evaluate_imagination.levers import lever_rows, plot_levers
from worldenv_core.contract import TaskContract
from worldenv_core.envs.replay import PairedReplayJob, by_start, replay_context
from worldenv_core.files import write_text_atomic
from worldenv_core.imagination.pairs import store_pair_frames
from worldenv_core.imagination.verdict import (as_judged_by, eta_curve, evaluator_metrics, frame_metrics, imagine, judge,
                                               pair, per_task, replay_eta, terminal_reward, verdict_metrics)
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.parallel import run_jobs
from worldenv_core.report import ReportContext, markdown_table, titled
from worldenv_core.viz import figure, montage_video, save_figure

BATCH_CONTEXTS = 16  # contexts imagined together (x rollouts each): bounds memory at any scale
# The targets for the headline policy (docs/fidelity.md).
TARGETS = {"auroc": (">=", 0.90), "f1": (">=", 0.80), "hack_rate": ("<=", 0.10), "max_task_gap": ("<=", 0.05),
           "spearman": (">=", 0.80)}


@dataclass(frozen=True)
class Variant:
    name: str  # "<policy ref>@<noise scale>"
    path: str  # the policy checkpoint
    noise_scale: float
    paired: bool = True  # replay its imagined rollouts in the real simulator (else: imagination + closed loop)


def pair_variant(cfg, contract: TaskContract, v: Variant, env, contexts: list[PairedContext], encode, reflector: str,
                 eta: float, device, gifs: int, out: Path, frames_dir: Path | None = None) -> dict:
    """One policy: imagine `rollouts` per context, replay each in the real simulator (if `v.paired`)
    and pair them; `closed_loop_rollouts` per context of the policy acting on real frames. With
    `frames_dir`, both sides' frames at every check are kept there (further reflectors judge them)."""
    policy, _ = load_checkpoint(v.path, "policy", contract, device=str(device))
    g = torch.Generator().manual_seed(cfg.seed)
    keep, n = sorted({0, *cfg.horizons}), cfg.rollouts
    shown = {c * n for c in range(min(gifs, len(contexts)))}  # the first rollout of the first contexts: GIFs
    full = set(range(len(contexts) * n)) if frames_dir is not None and v.paired else shown  # every check's frame
    runs = []
    for b in range(0, len(contexts), BATCH_CONTEXTS):
        part = contexts[b:b + BATCH_CONTEXTS]
        got = imagine(policy, env, [c.context for c in part], n, encode, g, v.noise_scale, keep,
                      {r - b * n for r in full if b * n <= r < (b + len(part)) * n})
        for r in got:
            r.context += b
        runs += got
    paired = range(n) if v.paired else range(0)
    jobs = [PairedReplayJob(contract, pc.start, actions=tuple(runs[i * n + k].actions for k in paired),
                            keep=tuple(None if i * n + k in full else tuple(keep) for k in paired),
                            reflector_path=reflector, policy_path=v.path if cfg.closed_loop_rollouts else None,
                            closed_loop_seeds=tuple(cfg.seed * 1_000_003 + i * 101 + k for k in range(cfg.closed_loop_rollouts)),
                            noise_scale=v.noise_scale, horizon=cfg.horizon)
            for i, pc in enumerate(contexts)]
    real = by_start(run_jobs(replay_context, jobs, workers=cfg.workers, launcher=cfg.launcher,
                             desc=f"real replay {v.name}", ray_address=cfg.ray_address, progress=cfg.progress, unit="ctx"))
    rows, closed = [], []
    for i, pc in enumerate(contexts):
        res = real[pc.start.key]
        closed += [c["success"] for c in res["closed_loop"]]
        for k, rep in enumerate(res["replays"]):
            run = runs[i * n + k]
            row = pair(run, rep, pc.start.task_id, pc.kind, v.name, contract.chunk)
            row["start"] = pc.start.key
            # only at `horizons`: with store_frames every check's frame is here, and SSIM is not free
            real_at = {h: rep["frames"][h] for h in cfg.horizons if h in rep["frames"]}
            row["frames"] = {str(h): m for h, m in frame_metrics(run.frames, real_at).items()}
            row["copy"] = {str(h): m for h, m in frame_metrics({s: rep["frames"][0] for s in real_at}, real_at).items()}
            rows.append(row)
            if frames_dir is not None:
                store_pair_frames(frames_dir / f"{len(rows) - 1:04d}.npz", run.frames, rep["frames"])
            if i * n + k in shown:
                steps = sorted(set(run.frames) & set(rep["frames"]))
                j = judge(row, eta)
                verdict = (f"imagined-{'success' if j['imagined_success'] else 'failure'}_"
                           f"real-{'success' if j['real_success'] else 'failure'}")
                montage_video([np.stack([run.frames[s] for s in steps]), np.stack([rep["frames"][s] for s in steps])],
                              out / "videos" / f"{v.name.replace('/', '_')}_ctx{i:03d}_task{pc.start.task_id:02d}_{verdict}.gif",
                              max_frames=len(steps), fps=4)
    said = [any(x > eta for x in r.scores[1:]) for r in runs]  # the imagined verdicts at eta, paired or not
    return {"rows": rows, "closed_loop": closed, "imagined_rollouts": len(runs), "imagined_success": float(np.mean(said)),
            "imagined_reward": float(np.mean([terminal_reward(r.scores, eta) for r in runs])),
            "real_episodes": len(rows) + len(closed)}


def max_task_gap(rows: list[dict], eta: float) -> float | None:
    """The largest |imagined - real| success of any task at `eta`."""
    tasks = per_task(rows, eta)
    return max(abs(t["imagined_success"] - t["real_success"]) for t in tasks.values()) if tasks else None


def judged(rows: list[dict], eta: float) -> dict:
    """A further reflector's verdicts on the pairs: agreement at its eta, worst task, eta chosen on replays."""
    return {"eta": eta, **verdict_metrics(rows, eta, intervals=True), "max_task_gap": max_task_gap(rows, eta), "replay_eta": replay_eta(rows)}


def summarise(results: dict, names: list[str], eta: float, horizons: list[int], judges: tuple[Judge, ...] = ()) -> dict:
    """The headline (the first policy's pairs), per context kind and task, frames by horizon, the
    world model as a policy evaluator over all policies, and the further reflectors' verdicts on
    the headline's pairs."""
    per_policy = {}
    for name in names:
        m = verdict_metrics(results[name]["rows"], eta, intervals=True)
        closed = results[name]["closed_loop"]
        per_policy[name] = {**m, "imagined_success": results[name].get("imagined_success", m.get("imagined_success")),
                            "imagined_reward": results[name].get("imagined_reward"),
                            "closed_loop_success": float(np.mean(closed)) if closed else None,
                            "real_episodes": results[name]["real_episodes"]}
    rows = results[names[0]]["rows"]
    tasks = per_task(rows, eta)
    frames = {}
    for h in horizons:
        got = [r for r in rows if str(h) in r["frames"]]
        frames[h] = {"n": len(got), **{f"{who}_{what}": float(np.mean([r[key][str(h)][j] for r in got])) if got else None
                                       for who, key in (("model", "frames"), ("copy", "copy"))
                                       for j, what in enumerate(("psnr", "ssim"))}}
    head = per_policy[names[0]]
    return {"headline_policy": names[0], "eta": eta,
            "headline": {**head, "max_task_gap": max_task_gap(rows, eta)},
            "by_context": {kind: verdict_metrics([r for r in rows if r["context_kind"] == kind], eta)
                           for kind in ("init", "episode")},
            "replay_eta": replay_eta(rows),  # the lever: eta chosen on replays (2-fold over contexts)
            "eta_curve": eta_curve(rows),
            "evaluator": evaluator_metrics(per_policy, "closed_loop_success"),
            "evaluator_paired": evaluator_metrics(per_policy, "real_success"),
            # mean imagined reward ranks policies even where no imagined rollout reaches eta
            "evaluator_reward": evaluator_metrics(per_policy, "closed_loop_success", "imagined_reward"),
            "real_episodes": sum(r["real_episodes"] for r in results.values() if r),
            "imagined_rollouts": sum(r["imagined_rollouts"] for r in results.values() if r),
            "per_policy": per_policy, "per_task": tasks, "frames": frames,
            "judges": {j.name: {**judged([as_judged_by(r, j.name) for r in rows], j.eta),
                                "evaluator_paired": judged_evaluator(results, names, j)} for j in judges if rows}}


def _ci(m: dict, name: str) -> str:
    """' [low, high]': the 95 % interval over contexts, where the run has one (runs before it did not)."""
    ci = m.get(f"{name}_ci95")
    return f" [{_num(ci[0], 2)}, {_num(ci[1], 2)}]" if ci else ""


def judged_evaluator(results: dict, names: list[str], j: Judge) -> dict:
    """The policy evaluator on paired replays as further reflector `j` judges them: each paired
    policy's imagined success against the real success of the same actions (by j's stops)."""
    per_policy = {n: verdict_metrics([as_judged_by(r, j.name) for r in results[n]["rows"]], j.eta)
                  for n in names if results[n]["rows"] and all(j.name in r["more_reflectors"] for r in results[n]["rows"])}
    return evaluator_metrics(per_policy, "real_success")


def write_outputs(stage, summary: dict, results: dict, work: Path) -> None:
    out = stage.manifest.root / "evaluate_imagination" / Path(work).name
    out.mkdir(parents=True, exist_ok=True)
    for name, data in (("fidelity.json", summary), ("pairs.json", results)):
        stage.add_output(write_text_atomic(out / name, json.dumps(data, indent=1, default=str)), kind="report")
    stage.add_output(plot_policies(summary, out / "imagined_vs_real.png"), kind="plot")
    if summary.get("eta_curve"):
        stage.add_output(plot_eta_curve(summary, out / "verdict_vs_eta.png"), kind="plot")
    for gif in sorted((Path(work) / "videos").glob("*.gif")):
        stage.add_output(gif, kind="video")


def plot_policies(summary: dict, path: Path) -> Path:
    """Imagined against real success per policy: on the diagonal, the world model ranks and
    scores policies as the real simulator does."""
    fig, ax = figure(figsize=(5, 5))
    for name, m in summary["per_policy"].items():
        for key, marker, label in (("closed_loop_success", "o", "closed loop"), ("real_success", "x", "paired replay")):
            if m.get(key) is not None:
                ax.scatter(m[key], m["imagined_success"], marker=marker, label=label)
                ax.annotate(name, (m[key], m["imagined_success"]), fontsize=7)
    handles = {h.get_label(): h for h in ax.collections}
    ax.legend(handles.values(), handles.keys(), loc="upper left")
    ax.plot([0, 1], [0, 1], "k--", lw=0.8)
    ax.set(xlim=(-0.02, 1.02), ylim=(-0.02, 1.02), xlabel="real success", ylabel="imagined success",
           title="the world model as a policy evaluator")
    return save_figure(fig, path)


def plot_eta_curve(summary: dict, path: Path) -> Path:
    """F1, precision and recall of the imagined verdict, and imagined against real success, at
    every eta (the headline policy's pairs); the reflector's own eta marked."""
    curve = summary["eta_curve"]
    fig, ax = figure(figsize=(6, 3.5))
    etas = [c["eta"] for c in curve]
    for key, style in (("f1", "-"), ("precision", "--"), ("recall", ":"), ("imagined_success", "-."),
                       ("real_success", "-")):
        ax.plot(etas, [c[key] for c in curve], style, label=key.replace("_", " "), lw=2.5 if key == "f1" else 1.2)
    ax.axvline(summary["eta"], color="k", lw=0.8)
    ax.set(xlabel="eta", ylim=(-0.02, 1.02), title=f"imagined verdict against real, {summary['headline_policy']}")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def _pct(x) -> str:
    return "" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{100 * x:.1f} %"


def _num(x, digits: int = 3) -> str:
    return "" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def meets(key: str, value: float) -> bool:
    """Whether a verdict figure meets its target in TARGETS."""
    op, target = TARGETS[key]
    return value >= target if op == ">=" else value <= target


def _mark(key: str, value) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return ""
    op, target = TARGETS[key]
    return " (met)" if meets(key, value) else f" (target {op} {target:g})"


def _sampler(tags: dict) -> str:
    steps, noise = tags.get("sampling_steps"), tags.get("sampler_noise")
    return f"{steps or 'default'}, {'default' if noise is None else f'{noise:g}'}"


def _evaluator(ev: dict) -> str:
    return f"{_num(ev['spearman'], 2)} / {_pct(ev['mae'])} ({ev['policies']})" if ev.get("policies", 0) >= 2 else "-"


def _real_frames(m: dict) -> str:
    """The reflector on the real frames: asked at the imagined verdict's check / stopping on its own."""
    return f"{_num(m['real_frames_f1'])} / {_num(m.get('real_stop_f1'))}"


def _replay_eta(r: dict) -> str:
    if not r.get("etas"):
        return ""
    return f"{_num(r['f1'])} / {_pct(r['hack_rate'])} ({', '.join(f'{e:g}' for e in r['etas'])})"


def _fidelity_path(record) -> str:
    return next((a.path for a in record.files("report") if Path(a.path).name == "fidelity.json"), record.id)


def section(ctx: ReportContext, limit: int = 8) -> list[str]:
    """One row per recent run (the before/after table of the levers), then the newest run's
    policies, tasks, frames along the pairs, plot and GIFs."""
    # pairs on training contexts are a reflector's training data (contexts=training), not a measurement
    runs = [r for r in ctx.find("evaluate_imagination") if r.tags.get("contexts") != "training"]
    # a re-run into the same work dir (rescoring its pairs with more reflectors) rewrites the same
    # report: one row per work dir, at the place of its newest run
    newest_of = {_fidelity_path(r): r for r in runs}
    runs = [r for r in runs if newest_of[_fidelity_path(r)] is r][-limit:]
    if not runs:
        return []
    rows, judgements = [], []
    for r in runs:
        s = ctx.report_json(r, "fidelity.json")
        if not s:
            continue
        h, ev = s["headline"], s["evaluator"]
        c = r.config.get("contexts", {})
        pairing = f"{c.get('init_states', 0)} init, {c.get('episodes_per_task', 0)}x{c.get('episode_frames', 0)} mid; {_sampler(r.tags)}"
        judgements += [(r.tags.get("worldsim"), f"{name}\n{pairing}", m)
                       for name, m in [(r.tags.get("reflector"), h), *s.get("judges", {}).items()]]
        rows.append([r.tags.get("worldsim"), r.tags.get("reflector"), _num(s["eta"], 2), _sampler(r.tags),
                     s["headline_policy"], h["rollouts"], _num(h["auroc"]) + _mark("auroc", h["auroc"]) + _ci(h, "auroc"),
                     _num(h["f1"]) + _mark("f1", h["f1"]) + _ci(h, "f1"), _pct(h["hack_rate"]) + _mark("hack_rate", h["hack_rate"]),
                     f"{_pct(h['imagined_success'])} / {_pct(h['real_success'])}",
                     _pct(h["max_task_gap"]) + _mark("max_task_gap", h["max_task_gap"]), _num(h["timing_error_median"], 0),
                     _real_frames(h), _replay_eta(s.get("replay_eta", {})),
                     f"{_num(ev['spearman'], 2)}{_mark('spearman', ev['spearman'])} / {_pct(ev['mae'])} ({ev['policies']})"
                     + (f"; by reward {_num(s['evaluator_reward']['spearman'], 2)}" if s.get("evaluator_reward") else ""),
                     s["real_episodes"]])
    lines = ["The imagined verdict (world model + reflector) against the real outcome of the same actions "
             "(`make fidelity`; contexts no model trained on). AUROC: the imagined reward against real success; "
             "[low, high]: 95 % intervals resampling whole contexts (a context's rollouts share its start); "
             "F1 and hack rate (imagined successes that fail in reality) at eta; real-frame F1: the reflector on the "
             "real frames of the same actions, asked at the imagined verdict's check and stopping them on its own "
             "(low: the reflector is wrong; high while F1 is low: the world model is); "
             "eta chosen on replays: each half of the contexts judged at the eta with the best F1 on the other half's pairs; "
             "evaluator: imagined against closed-loop real success over the policies.", "",
             *markdown_table(["world model", "reflector", "eta", "sampler (steps, noise)", "policy", "pairs", "AUROC",
                              "F1", "hack rate", "imagined / real success", "max task gap", "timing error (median steps)",
                              "real-frame F1 at the verdict / own stop", "eta chosen on replays: F1 / hack rate (etas)", "evaluator Spearman / MAE (policies)", "real episodes"], rows)]
    if judgements:
        plot_levers(lever_rows(judgements), ctx.out / "fidelity_levers.png")
        lines += ["", "Every world model and reflector the held-out pairs were judged with (a run's reflector and the "
                  "further reflectors on its pairs), against the targets:", "", "![verdict by lever](fidelity_levers.png)"]
    newest = runs[-1]
    s = ctx.report_json(newest, "fidelity.json")
    if s:
        lines += ["", f"Newest run (`{newest.id}`), per policy:", "", *markdown_table(
            ["policy", "imagined success", "imagined reward", "paired real success", "closed-loop real success", "AUROC", "F1", "hack rate",
             "real episodes"],
            [[n, _pct(m["imagined_success"]), _num(m.get("imagined_reward")), _pct(m.get("real_success")), _pct(m["closed_loop_success"]),
              _num(m.get("auroc")), _num(m.get("f1")), _pct(m.get("hack_rate")), m["real_episodes"]]
             for n, m in s["per_policy"].items()])]
        if s.get("judges"):
            first = {"eta": s["eta"], **s["headline"], "replay_eta": s.get("replay_eta", {})}
            first["evaluator_paired"] = s.get("evaluator_paired", {})
            lines += ["", "Reflectors judging the same pairs (the headline's imagined rollouts and their real replays; "
                      "the first terminates the imagined rollouts, each judges at its own eta; evaluator: over the "
                      "paired policies):", "", *markdown_table(
                ["reflector", "eta", "AUROC", "F1", "hack rate", "imagined / real success", "max task gap",
                 "real-frame F1 at the verdict / own stop", "eta chosen on replays: F1 / hack rate (etas)",
                 "evaluator Spearman / MAE (policies)"],
                [[name, _num(m["eta"], 2), _num(m["auroc"]), _num(m["f1"]), _pct(m["hack_rate"]),
                  f"{_pct(m['imagined_success'])} / {_pct(m['real_success'])}", _pct(m["max_task_gap"]),
                  _real_frames(m), _replay_eta(m.get("replay_eta", {})), _evaluator(m.get("evaluator_paired") or {})]
                 for name, m in [(newest.tags.get("reflector"), first), *s["judges"].items()]])]
        lines += ["", "By context kind and task (headline policy):", "", *markdown_table(
            ["contexts", "pairs", "imagined success", "real success", "AUROC", "F1"],
            [[k, m["rollouts"], _pct(m.get("imagined_success")), _pct(m.get("real_success")), _num(m.get("auroc")),
              _num(m.get("f1"))] for k, m in s["by_context"].items()]
            + [[f"task {t}", m["rollouts"], _pct(m["imagined_success"]), _pct(m["real_success"]), "", ""]
               for t, m in s["per_task"].items()])]
        lines += ["", "Imagined against real frames along the pairs (copy: the context frame):", "", *markdown_table(
            ["steps", "pairs", "PSNR model / copy", "SSIM model / copy"],
            [[h, f["n"], f"{_num(f['model_psnr'], 2)} / {_num(f['copy_psnr'], 2)}",
              f"{_num(f['model_ssim'])} / {_num(f['copy_ssim'])}"] for h, f in s["frames"].items()])]
        for art in newest.files("plot"):
            plot = ctx.copy(art.path, f"fidelity_{Path(art.path).name}", folder=".")
            lines += ["", f"![{Path(art.path).stem.replace('_', ' ')}]({plot})"] if plot else []
        gifs = [g for g in (ctx.copy(a.path, f"fidelity_{Path(a.path).name}") for a in newest.files("video")) if g]
        if gifs:
            lines += ["", "Imagined | real, the same actions: " + " ".join(f"![pair]({g})" for g in gifs)]
    return titled("Verdict fidelity: imagined against real", lines)
