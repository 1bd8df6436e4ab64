"""One report per experiment, rebuilt from its manifest after every evaluation:
`<experiment>/report/report.md` + `success.png`.

* success per task in the real simulator, SFT vs post-trained, under oracle / fixed / reflector
  termination (the paper's Tables 1 and 3), from the newest evaluate record of each pair;
* ablations where they were run (post-training on a world model without extra data; the
  reflector without a reward head), each marked by its record's tags;
* world-model fidelity and reflector accuracy from their stages' reports;
* post-training curve (real success vs iteration) and wall time per stage.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from worldenv_core.manifest import Manifest, StageRecord

log = logging.getLogger(__name__)
TERMINATIONS = ("oracle", "fixed", "reflector")
POLICIES = ("sft", "post_trained")


def own_suite_evaluations(manifest: Manifest, task: str, **tags) -> list[StageRecord]:
    """The task's evaluations on its own suite (those on another suite carry an `eval_suite` tag
    and have their own table)."""
    return [r for r in manifest.find("evaluate", task=task, **tags) if "eval_suite" not in r.tags]


def _newest(records: list[StageRecord], **tags) -> StageRecord | None:
    found = [r for r in records if all(r.tags.get(k) == v for k, v in tags.items())]
    return found[-1] if found else None


def _report_json(manifest: Manifest, record: StageRecord | None, name: str) -> dict | None:
    if record is None:
        return None
    for art in record.files("report"):
        if Path(art.path).name == name:
            path = manifest.root / art.path
            return json.loads(path.read_text()) if path.exists() else None
    return None


def success_table(manifest: Manifest, task: str) -> tuple[list[str], dict]:
    evals = own_suite_evaluations(manifest, task)
    cells = {}  # (policy, termination) -> summary
    for policy in POLICIES:
        for term in TERMINATIONS:
            rec = _newest(evals, policy=policy, termination=term)
            if rec is None and policy == "sft":  # records from before the policy tag existed
                rec = _newest([r for r in evals if "policy" not in r.tags], termination=term)
            summary = _report_json(manifest, rec, "results.json")
            if summary:
                cells[(policy, term)] = summary
    if not cells:
        return ["No evaluation yet: `python -m stages.evaluate +task=... termination=oracle`."], cells
    cols = [k for k in ((p, t) for t in TERMINATIONS for p in POLICIES) if k in cells]
    tasks = sorted({(r["task_id"], r["task"]) for s in cells.values() for r in s["per_task"]})
    lines = ["| task | " + " | ".join(f"{p} / {t}" for p, t in cols) + " |", "|---|" + "---|" * len(cols)]
    for tid, name in tasks:
        row = []
        for key in cols:
            r = next((r for r in cells[key]["per_task"] if r["task_id"] == tid), None)
            row.append(f"{100 * r['success_rate']:.0f} %" if r else "")
        lines.append(f"| {tid} {name} | " + " | ".join(row) + " |")
    lines.append("| **all** | " + " | ".join(f"**{100 * cells[k]['success_rate']:.1f} %**" for k in cols) + " |")
    n = {cells[k]["init_states"] for k in cols}
    lines += ["", f"(first {'/'.join(map(str, sorted(n)))} benchmark init states per task)"]
    lines += _paired_lines(manifest, evals)
    for policy in POLICIES:
        refl = cells.get((policy, "reflector"))
        if refl and "reflector_termination" in refl:
            t = refl["reflector_termination"]
            lines += [f"{policy}: reflector `{_short(refl['reflector'])}` stops in the real simulator (eta {refl['eta']}): "
                      f"termination F1 {t['f1']:.3f}, median timing error {t['timing_error_median']:.0f} steps, "
                      f"{t['false_stops']} false stops, {t['missed_successes']} missed successes."]
    return lines, cells


def _paired_lines(manifest: Manifest, evals: list[StageRecord]) -> list[str]:
    """SFT vs post-trained on the same episodes, per termination: which episodes only one of them
    solved, and the exact McNemar p-value (is the difference more than chance?)."""
    from worldenv_core.metrics import paired_success_test

    lines = []
    for term in TERMINATIONS:
        eps = [_report_json(manifest, _newest(evals, policy=p, termination=term), "episodes.json") for p in POLICIES]
        if not all(eps):
            continue
        sft, post = ({(e["task_id"], e["init_state"]): e["success"] for e in es} for es in eps)
        t = paired_success_test(sft, post)
        if t["episodes"]:
            lines.append(f"{term}, paired over the {t['episodes']} episodes both policies ran: {t['only_a']} solved "
                         f"by SFT only, {t['only_b']} by the post-trained policy only; exact McNemar p = {t['p_value']:.3f}.")
    return [""] + lines if lines else []


def _short(path: str) -> str:
    """<stage>/<work dir> of a checkpoint path: which run it came from, without machine paths."""
    parts = Path(path).parts
    return "/".join(parts[-3:-1]) if len(parts) >= 3 else str(path)


def _input(record: StageRecord, stage: str, by_id: dict) -> StageRecord | None:
    """The record of `stage` that `record` read (by_id: the manifest's records by id, read once)."""
    return next((by_id[i] for i in record.inputs if i in by_id and by_id[i].stage == stage), None)


def _input_tags(record: StageRecord, stage: str, by_id: dict) -> dict:
    found = _input(record, stage, by_id)
    return found.tags if found else {}


def _history(manifest: Manifest, record: StageRecord) -> list[dict]:
    """A post_train_loop run's per-iteration log: the training.json written beside its plot."""
    for art in record.files("plot"):
        path = (manifest.root / art.path).with_suffix(".json")
        if path.exists():
            return json.loads(path.read_text())
    return []


def _span(history: list[dict], key: str, n: int = 5) -> str:
    """Mean of `key` over the first and the last n iterations: 'first -> last'."""
    vals = [h[key] for h in history if key in h and h.get("step", 0) > 0]
    if not vals:
        return ""
    k = min(n, max(1, len(vals) // 2))
    return f"{sum(vals[:k]) / k:.3g} -> {sum(vals[-k:]) / k:.3g}"


def _fixed(record: StageRecord) -> str:
    """The imagined evaluation on fixed contexts and noise: first and last evaluation point."""
    rew, ok = record.metrics.get("imagined_reward", {}), record.metrics.get("imagined_success", {})
    if len(rew) < 2:
        return "not run"
    a, b = min(rew, key=int), max(rew, key=int)
    return f"{rew[a]:.3f} -> {rew[b]:.3f}, {ok[a]:.3f} -> {ok[b]:.3f}"


def post_training_table(manifest: Manifest, runs: list[StageRecord], out: Path) -> list[str]:
    """One row per post_train_loop run: its settings, which world model and reflector it imagined
    with (so the "without extra data" ablation shows as its own row), and how the imagined
    reward, the reflector's success rate and the real success moved; the newest run's curves."""
    lines = ["| eta | N | iterations | world model data | reflector data | imagined reward (first 5 -> last 5 it.) "
             "| reflector success rate | episode length | fixed contexts: imagined reward, success (SFT -> last) "
             "| real success by iteration | wall s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    by_id = {r.id: r for r in manifest.records()}
    for r in runs:
        h = _history(manifest, r)
        curve = ", ".join(f"{k}: {100 * v:.0f} %" for k, v in r.metrics.get("real_success", {}).items()) or "not run"
        lines.append(f"| {r.tags.get('eta')} | {r.tags.get('n_rollouts')} | {r.metrics.get('iterations')} "
                     f"| {_input_tags(r, 'train_worldsim', by_id).get('data', '?')} "
                     f"| {_input_tags(r, 'train_reflector', by_id).get('data', '?')} | {_span(h, 'mean_reward')} "
                     f"| {_span(h, 'reflector_success_rate')} | {_span(h, 'episode_length')} | {_fixed(r)} | {curve} "
                     f"| {r.wall_time_s:.0f} |")
    # The paper's Figure 3 needs the real success curve: the newest run that evaluated in the loop.
    shown = next((r for r in reversed(runs) if len(r.metrics.get("real_success", {})) > 1), runs[-1])
    history = _history(manifest, shown)
    if history:  # redrawn from the run's log, so older runs get the current layout too
        from worldenv_core.training import plot_history

        name = _short(str(shown.files("plot")[0].path))
        plot_history(history, out / "post_training.png", f"post_train_loop {name}")
        lines += ["", f"![post-training curves of `{name}`](post_training.png)"]
    return lines


def _producer(record: StageRecord, records: list[StageRecord]) -> StageRecord:
    """The first record of the same stage whose outputs hold this one's trained weights or episodes
    (by content): the run that did the work a later re-run found finished."""
    made = {a.sha256 for a in record.outputs  # the weights, not config.json: its metadata names the run
            if a.kind == "episodes" or (a.kind == "checkpoint" and a.path.endswith(".safetensors"))}
    return next((r for r in records if made and r.stage == record.stage
                 and made <= {a.sha256 for a in r.outputs}), record)


def _reward_kind(loop: StageRecord, by_id: dict) -> str:
    """Trained reward head (our reflector) or a prompted VLM's yes/no (the paper's "w/o reward head")."""
    refl = _input(loop, "train_reflector", by_id)
    target = str(((refl.config if refl else {}).get("reflector") or {}).get("_target_", ""))
    return "VLM yes/no" if "VLMYesNo" in target else "trained head"


def ablation_table(manifest: Manifest, task: str, limit: int = 8) -> list[str]:
    """The paper's Table 2 from what was run: every evaluated policy (SFT and each post-trained
    one, by checkpoint), whether its LOOP's world model saw the extra policy-rollout data, which
    reward it had, and the imagined reward it optimised; each row on the init states it was
    evaluated on, so only rows with the same count compare."""
    by_id = {r.id: r for r in manifest.records()}
    rows: dict[tuple, dict] = {}  # (checkpoint work dir, init states) -> {termination: success}, newest wins
    loops: dict[tuple, StageRecord | None] = {}
    for ev in own_suite_evaluations(manifest, task):
        summary = _report_json(manifest, ev, "results.json")
        loop = _input(ev, "post_train_loop", by_id)
        if not summary or (loop is None and ev.tags.get("policy") != "sft"):
            continue
        key = (_short(summary["policy"]), summary["init_states"])
        rows.setdefault(key, {})[summary["termination"]] = summary["success_rate"]
        loops[key] = loop
    if not any(loops.values()):
        return []
    lines = ["| policy | extra data for the world model | reward | imagined reward, success (SFT -> last) "
             "| init states per task | " + " | ".join(TERMINATIONS) + " |", "|---|---|---|---|---|---|---|---|"]
    newest = list(rows)[-limit:]  # evaluated most recently; keys keep first-evaluation order
    for key in sorted(newest, key=lambda k: (k[1], loops[k] is not None)):
        loop, cells = loops[key], rows[key]
        data = _input_tags(loop, "train_worldsim", by_id).get("data") if loop else None
        extra = {"expert+policy": "yes", "expert": "no (expert demos only)"}.get(data, "")
        reward = f"{_reward_kind(loop, by_id)}, eta {loop.tags.get('eta')}" if loop else ""
        lines.append(f"| {'SFT' if loop is None else 'post-trained'} `{key[0]}` | {extra} | {reward} "
                     f"| {_fixed(loop) if loop else ''} | {key[1]} | "
                     + " | ".join(f"{100 * cells[t]:.1f} %" if t in cells else "" for t in TERMINATIONS) + " |")
    return lines


def video_section(manifest: Manifest, task: str, out: Path, per_policy: int = 3) -> list[str]:
    """A few episodes of the newest evaluation of each policy under reflector termination (else
    oracle), successes first, copied beside the report so the folder stands on its own."""
    import shutil

    lines = []
    for policy in POLICIES:
        evals = own_suite_evaluations(manifest, task, policy=policy)
        rec = _newest(evals, termination="reflector") or _newest(evals, termination="oracle")
        videos = sorted(rec.files("video"), key=lambda a: ("failure" in a.path, a.path)) if rec else []
        for art in videos[:per_policy]:
            src = manifest.root / art.path
            if not src.exists():
                continue
            dst = out / "videos" / f"{policy}_{rec.tags['termination']}_{src.name}"
            dst.parent.mkdir(exist_ok=True)
            shutil.copyfile(src, dst)
            lines.append(f"![{policy}, {rec.tags['termination']} termination: {src.stem}](videos/{dst.name})")
    return lines


def other_suites_table(manifest: Manifest, task: str) -> list[str]:
    """Policies of this task evaluated on another registered suite with the same tasks (`evaluate
    eval_suite=...`, e.g. a LIBERO-PRO perturbation), newest per (policy, suite, termination)."""
    newest = {}
    for r in manifest.find("evaluate", task=task):
        if "eval_suite" in r.tags:
            newest[(r.tags.get("policy"), r.tags["eval_suite"], r.tags["termination"])] = r
    lines = []
    for (policy, suite, term), r in sorted(newest.items(), key=lambda kv: tuple(map(str, kv[0]))):
        summary = _report_json(manifest, r, "results.json")
        if summary:
            lines.append(f"| {policy} | {suite} | {term} | {summary.get('max_steps', '')} | "
                         f"{100 * summary['success_rate']:.1f} % | {summary['episodes']} |")
    if not lines:
        return []
    return ["| policy | evaluated on suite | termination | step limit | success | episodes |",
            "|---|---|---|---|---|---|", *lines]


def write_report(experiment_dir: str | Path, task: str) -> Path:
    manifest = Manifest(experiment_dir)
    out = manifest.root / "report"
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# {task}: experiment report", "", "## Success in the real simulator", ""]
    table, cells = success_table(manifest, task)
    lines += table
    if cells:
        _plot_success(cells, out / "success.png")
        lines += ["", "![success](success.png)"]

    others = other_suites_table(manifest, task)
    if others:
        lines += ["", f"## Evaluated on other suites (trained on {task}'s)", ""] + others

    videos = video_section(manifest, task, out)
    if videos:
        lines += ["", "Episodes (first init states of each task; GIFs):", ""] + videos
    ablations = ablation_table(manifest, task)
    if ablations:
        lines += ["", "## Ablations (the paper's Table 2, as far as run)", ""] + ablations
    loop = manifest.find("post_train_loop", task=task)
    if loop:
        lines += ["", "## Post-training (LOOP in imagination)", ""] + post_training_table(manifest, loop[-6:], out)

    worldsims = [(ws, _report_json(manifest, ws, "fidelity.json")) for ws in
                 (_newest(manifest.find("train_worldsim", task=task, data=d)) for d in ("expert+policy", "expert")) if ws]
    if any(fid for _, fid in worldsims):  # newest of each training set: the "w/o extra data" ablation side by side
        lines += ["", "## World simulator (open loop on held-out episodes)", "",
                  "| data | horizon | PSNR model | PSNR copy-last | SSIM model | SSIM copy-last | SSIM plain decoding |",
                  "|---|---|---|---|---|---|---|"]
        for ws, fid in worldsims:
            for h, v in (fid or {}).get("fidelity", {}).items():
                plain = f"{v['plain_ssim']:.3f}" if "plain_ssim" in v else "-"
                lines.append(f"| {ws.tags.get('data')} | {h} | {v['model_psnr']:.2f} | {v['copy_psnr']:.2f} | "
                             f"{v['model_ssim']:.3f} | {v['copy_ssim']:.3f} | {plain} |")
    # Every recent reflector, not only the newest: evaluations and post-training name the one they used.
    reflectors = [(r, _report_json(manifest, r, "reflector_eval.json")) for r in manifest.find("train_reflector", task=task)[-4:]]
    reflectors = [(r, acc) for r, acc in reversed(reflectors) if acc]
    if reflectors:
        lines += ["", "## Reflector (held-out episodes, newest first)", "",
                  "| record | data | training | eta | held out | video | step accuracy | step F1 | step AUROC | "
                  "termination F1 |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r, acc in reflectors:
            train = r.config.get("train") or {}
            mine = train.get("mine") or {}
            training = ", ".join([f"{train.get('steps')} steps", f"label delay {train.get('label_delay', 0)}",
                                  f"mining every {mine['every']} > {mine['threshold']}" if mine.get("every") else "no mining"]
                                 + (["+ imagined replays"] if train.get("with_imagined") else []))
            ckpt = r.files("checkpoint")
            run = f"`{r.id}` ({_short(str(Path(ckpt[0].path).parent))})" if ckpt else f"`{r.id}`"  # the name evaluations give above
            for kind in ("real", "imagined"):
                if kind in acc:
                    p, t = acc[kind]["per_step"], acc[kind]["termination"]["all"]
                    lines.append(f"| {run} | {r.tags.get('data')} | {training} | {acc['eta']} | {acc['held_out_episodes']} "
                                 f"| {kind} | {p['accuracy']:.3f} | {p['f1']:.3f} | {p['auroc']:.3f} | {t['f1']:.3f} |")
            if "cross_validation" in acc:  # the eta the checkpoint carries, chosen without the held-out episodes
                cv = acc["cross_validation"]
                lines.append(f"| {run} | {r.tags.get('data')} | {training} | {cv['chosen_eta']} ({cv['folds']}-fold CV) "
                             f"| {acc['held_out_episodes']} | real | | | | {cv['real_termination_at_chosen_eta']['f1']:.3f} |")

    lines += ["", "## Wall time per stage", "",
              "Newest run of each; a re-run that found the work done is timed by the run that produced its files "
              "(its last sitting, if it was resumed).", "",
              "| stage | tags | record | wall s |", "|---|---|---|---|"]
    records = manifest.records()
    seen = {}
    for r in records:
        if r.tags.get("task") == task:
            seen[(r.stage, json.dumps(r.tags, sort_keys=True))] = r
    for r in seen.values():
        made = _producer(r, records)
        tags = ", ".join(f"{k}={v}" for k, v in r.tags.items() if k != "task")
        lines.append(f"| {r.stage} | {tags} | `{made.id}` | {made.wall_time_s:.0f} |")
    path = out / "report.md"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return path


def _plot_success(cells: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = [k for k in ((p, t) for t in TERMINATIONS for p in POLICIES) if k in cells]
    tasks = sorted({r["task_id"] for s in cells.values() for r in s["per_task"]})
    fig, ax = plt.subplots(figsize=(max(6, len(tasks) * 0.9), 3.2))
    width = 0.8 / len(keys)
    for i, key in enumerate(keys):
        rates = {r["task_id"]: r["success_rate"] for r in cells[key]["per_task"]}
        ax.bar(np.arange(len(tasks)) + i * width, [100 * rates.get(t, 0) for t in tasks], width, label=" / ".join(key))
    ax.set_xticks(np.arange(len(tasks)) + 0.4 - width / 2, [str(t) for t in tasks])
    ax.set_xlabel("task")
    ax.set_ylabel("success %")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path.with_suffix(".tmp.png"))
    plt.close(fig)
    path.with_suffix(".tmp.png").replace(path)
