"""The cross-suite table: SFT against the post-trained policy on each suite's own experiment
(the paper's Table 1 across suites, and Table 3's terminations), with the paired McNemar test.

    python -m stages.suites outputs/suites libero_goal=outputs/libero_goal-small \
        libero_object=outputs/libero_object-small libero_spatial=outputs/libero_spatial-small

Each experiment's newest evaluations of `sft` and `post_trained` (on its own suite) are read
from its manifest; a suite without them shows as not run. A second table says which limit holds
where post-training does not gain, from the same manifests: the verdict on the SFT policy's paired
replays against the fidelity targets (AUROC >= 0.90, F1 >= 0.80, hack rate <= 10 %), imagined against real success of the same actions (the world
model's drift), what LOOP raised in imagination, and the real-simulator reference (`env=real`),
which bounds what RL can do at that budget. Writes `<out>/suites.{md,json}`.

The same table from the evaluations kept in the repository (no experiment directory, no simulator):
`results/suites.yaml` names, per row, each side's kept evaluation folders per termination, and per suite
the kept paired-replay run that gives its verdict; `make suites-table` writes `results/suites.md`.

    python -m stages.suites --kept results/suites.yaml

The perturbed-suite table (LIBERO-PRO) is `stages.suites_pro`.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from omegaconf import OmegaConf

from stages.evaluate.evaluation import own_suite_evaluations
from worldenv_core.evaluations import compare, pooled_episodes
from stages.evaluate_imagination.evaluation import TARGETS, meets
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.imagination.verdict import misattributed, verdict_metrics
from worldenv_core.manifest import Manifest
from worldenv_core.report import POLICIES, TERMINATIONS, ReportContext, markdown_table, newest


def suite_row(experiment: str | Path, task: str) -> dict:
    """Per termination: SFT and post-trained success and the paired test over the episodes both ran."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    evals = own_suite_evaluations(ctx)
    row = {"task": task, "experiment": str(experiment)}
    for term in TERMINATIONS:
        found = [newest(evals, policy=p, termination=term) for p in POLICIES]
        episodes = [ctx.report_json(r, "episodes.json") for r in found]
        if not all(episodes):
            continue
        sft, post = ({(e["task_id"], e["init_state"]): bool(e["success"]) for e in es} for es in episodes)
        row[term] = _paired(sft, post)
    return row


def _paired(sft: dict, post: dict) -> dict:
    test = compare(sft, post)
    return {"sft": test["a"], "post_trained": test["b"], **{k: test[k] for k in ("episodes", "only_a", "only_b", "p_value")}}


def _verdict_holds(h: dict) -> list[str]:
    """The limits a paired-replay headline shows: its figures off the fidelity targets, and the world
    model's drift (imagined against real success of the same actions)."""
    holds = []
    missed = [k for k in ("auroc", "f1", "hack_rate") if _num(h.get(k)) and not meets(k, h[k])]
    if missed:
        holds.append("verdict fidelity (" + ", ".join(missed) + " off target)")
    if _num(h.get("imagined_success")) and _num(h.get("real_success")):
        gap = h["imagined_success"] - h["real_success"]
        if abs(gap) > TARGETS["max_task_gap"][1]:
            holds.append(f"world-model drift (imagined - real {100 * gap:+.0f} points)")
    return holds


def _num(x) -> bool:
    """A measured figure: not missing, not NaN (an AUROC with no real success among the pairs)."""
    return x is not None and not (isinstance(x, float) and math.isnan(x))


def _first_last(curve: dict | None) -> tuple[float, float] | None:
    """A per-iteration metric ({"0": v, "10": v, ...}) as (first, last), or None if not recorded."""
    points = sorted(((int(k), v) for k, v in (curve or {}).items() if v is not None), key=lambda kv: kv[0])
    return (points[0][1], points[-1][1]) if points else None


def limits(experiment: str | Path, task: str) -> dict:
    """What each limit measured on one suite's experiment, and which of them hold. `verdict`: the
    newest paired-replay run on held-out contexts (its headline policy, normally SFT); `loop`: the
    newest LOOP in imagination; `reference`: the newest LOOP in the real simulator."""
    ctx = ReportContext(Manifest(experiment), task, Path(experiment) / "report")
    out, holds = {}, []
    fidelity = [r for r in ctx.find("evaluate_imagination") if r.tags.get("contexts", "held_out") == "held_out"]
    if fidelity:
        h = fidelity[-1].metrics.get("headline") or {}
        out["verdict"] = {k: h.get(k) for k in ("auroc", "f1", "hack_rate", "imagined_success", "real_success",
                                                 "rollouts")}
        holds += _verdict_holds(h)
    loop = newest(ctx.find("post_train_loop"), env="imagined") or newest(
        [r for r in ctx.find("post_train_loop") if "env" not in r.tags])
    if loop:
        out["loop"] = {k: _first_last(loop.metrics.get(k)) for k in ("imagined_reward", "imagined_success")}
        rise = out["loop"]["imagined_success"]
        if rise and rise[1] <= rise[0]:
            holds.append("no imagined gain to transfer")
    reference = newest(ctx.find("post_train_loop"), env="real")
    if reference:
        out["reference"] = {"real_success": _first_last(reference.metrics.get("real_success"))}
        rise = out["reference"]["real_success"]
        if rise and rise[1] <= rise[0]:
            holds.append("RL capacity (no real gain with the real simulator as environment)")
    out["holds"] = holds
    return out


def _pct(x: float | None) -> str:
    return f"{100 * x:.1f} %" if _num(x) else ""


def _arrow(pair: tuple[float, float] | None) -> str:
    return "" if not pair else f"{_pct(pair[0])} -> {_pct(pair[1])}"


def limits_table(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        lim = r.get("limits", {})
        v = lim.get("verdict") or {}
        verdict = (f"{v['auroc']:.2f} / {v['f1']:.2f} / {_pct(v['hack_rate'])} ({v['rollouts']})"
                   if v and None not in (v.get("auroc"), v.get("f1"), v.get("hack_rate")) else "not measured")
        same = f"{_pct(v.get('imagined_success'))} / {_pct(v.get('real_success'))}" if v else ""
        loop = lim.get("loop") or {}
        ref = lim.get("reference") or {}
        out.append([r["task"], verdict, same, _arrow(loop.get("imagined_success")),
                    _arrow(ref.get("real_success")) or "not run", "; ".join(lim.get("holds", [])) or "none measured"])
    return markdown_table(["suite", "verdict AUROC / F1 / hack rate (pairs)", "imagined / real success, same actions",
                           "LOOP: imagined success first -> last", "real-simulator reference: real success",
                           "limits that hold"], out)


def _termination_cells(row: dict, missing: str, p_format: str) -> list:
    """A row's oracle cells (SFT -> post-trained, gain, discordant pairs, p, episodes), then fixed and reflector."""
    o = row.get("oracle")
    cells = [f"{_pct(o['sft'])} -> {_pct(o['post_trained'])}", f"{100 * (o['post_trained'] - o['sft']):+.1f}",
             f"{o['only_a']} / {o['only_b']}", format(o["p_value"], p_format), o["episodes"]] if o else [missing, "", "", "", ""]
    for term in ("fixed", "reflector"):
        t = row.get(term)
        cells.append(f"{_pct(t['sft'])} -> {_pct(t['post_trained'])} (p {format(t['p_value'], p_format)})" if t else "")
    return cells


def table(rows: list[dict]) -> list[str]:
    out = [[r["task"], *_termination_cells(r, "not run", ".3g")] for r in rows]
    return markdown_table(["suite", "oracle: SFT -> post-trained", "gain (points)", "solved only by SFT / post-trained",
                           "McNemar p", "paired episodes", "fixed horizon", "reflector termination"], out)


def write(out: str | Path, experiments: dict[str, str]) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [{**suite_row(exp, task), "limits": limits(exp, task)} for task, exp in experiments.items()]
    (out / "suites.json").write_text(json.dumps(rows, indent=1))
    path = out / "suites.md"
    path.write_text("\n".join(["# SFT against post-trained, per suite", "", *table(rows), "",
                               "## Which limit holds", "",
                               "The verdict is the SFT policy's imagined rollouts judged against their real replays "
                               "(the fidelity targets: AUROC >= 0.90, F1 >= 0.80, hack rate <= 10 %, imagined - real "
                               "within 5 points); the reference is the same LOOP with the real simulator as "
                               "environment (`post_train_loop env=real`).", "", *limits_table(rows)]) + "\n")
    return path


def read_kept_spec(path: str | Path) -> dict:
    """results/suites.yaml, checked whole before anything is read: every named folder exists and is
    of its kind (an evaluation's results.json and episodes.json, a paired replay's fidelity.json)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file (the kept-evaluations spec, e.g. results/suites.yaml)")
    spec = OmegaConf.to_container(OmegaConf.load(path)) or {}
    root = path.parent
    for i, row in enumerate(spec.get("rows") or []):
        where = f"{path} rows[{i}]"
        for key in ("suite", "sft", "post_trained"):
            if key not in row:
                raise ConfigError(f"{where}: no {key!r}")
        for side in POLICIES:
            if "policy" not in row[side] or not any(t in row[side] for t in TERMINATIONS):
                raise ConfigError(f"{where}.{side}: needs 'policy' and the evaluations of at least one of "
                                  f"{', '.join(TERMINATIONS)}")
            for term in TERMINATIONS:
                for name in row[side].get(term) or []:
                    _kept(root, row["suite"], name, "episodes.json", where)
    for i, v in enumerate(spec.get("verdicts") or []):
        _kept(root, v["suite"], v["run"], "fidelity.json", f"{path} verdicts[{i}]")
    return spec


def _kept(root: Path, suite: str, name: str, needs: str, where: str) -> Path:
    folder = root / suite / name
    if not (folder / needs).is_file():
        raise ConfigError(f"{where}: {folder} has no {needs} (keep it with python -m analysis.keep)")
    return folder


def kept_rows(spec_path: str | Path) -> tuple[list[dict], list[dict]]:
    """The table's rows and the verdicts, from the kept evaluations a spec names (read_kept_spec)."""
    spec, root = read_kept_spec(spec_path), Path(spec_path).parent
    rows = []
    for entry in spec.get("rows") or []:
        task = entry["suite"]
        row = {"task": task, "sft_policy": entry["sft"]["policy"], "post_trained_policy": entry["post_trained"]["policy"],
               "note": entry.get("note", "")}
        for term in TERMINATIONS:
            names = [entry[side].get(term) for side in POLICIES]
            if all(names):
                sides = []
                for side, ns in zip(POLICIES, names):
                    episodes, setting = pooled_episodes(None, [str(root / task / n) for n in ns])
                    if (setting["suite"], setting["termination"]) != (task, term):
                        raise ConfigError(f"{spec_path}: {task} {side} {term}: the evaluations ran "
                                          f"{setting['suite']} with {setting['termination']} termination")
                    sides.append(episodes)
                row[term] = _paired(*sides)
        rows.append(row)
    verdicts = []
    for v in spec.get("verdicts") or []:
        fidelity = json.loads((root / v["suite"] / v["run"] / "fidelity.json").read_text())
        h, contexts = fidelity["headline"], v.get("contexts", "")
        pairs = root / v["suite"] / v["run"] / "pairs.json"
        pair_rows = json.loads(pairs.read_text())[fidelity["headline_policy"]]["rows"] if pairs.is_file() else []
        void = misattributed(pair_rows)
        if any(void):  # recomputed without them; the closed-loop runs were keyed the same way
            h = {**verdict_metrics([r for r, x in zip(pair_rows, void) if not x], fidelity["eta"]),
                 "closed_loop_success": None}
            contexts += (f" ({sum(void)} of {len(pair_rows)} pairs void: their init-state contexts were paired with another "
                         "task's replays; figures from the rest)")
        verdicts.append({"task": v["suite"], "run": v["run"], "contexts": contexts,
                         "policy": v.get("policy") or fidelity.get("headline_policy", ""),
                         **{k: h.get(k) for k in ("rollouts", "imagined_success", "real_success", "hack_rate",
                                                  "closed_loop_success")},
                         "holds": _verdict_holds(h) if h.get("rollouts") else ["not measured: no valid pair"]})
    return rows, verdicts


def kept_table(rows: list[dict], verdicts: list[dict]) -> list[str]:
    """results/suites.md: the rows (Table 1 per suite, Table 3's terminations where kept) and the verdicts."""
    lines = [[r["task"], r["sft_policy"], r["post_trained_policy"], *_termination_cells(r, "", ".2g"), r["note"]]
             for r in rows]
    out = markdown_table(["suite", "SFT policy", "post-trained policy", "oracle: SFT -> post-trained", "gain (points)",
                          "solved only by SFT / post-trained", "McNemar p", "paired episodes", "fixed horizon",
                          "reflector termination", "note"], lines)
    vrows = [[v["task"], v["policy"], v["contexts"], v["rollouts"], _pct(v["imagined_success"]), _pct(v["real_success"]),
              _pct(v["hack_rate"]), _pct(v["closed_loop_success"]), "; ".join(v["holds"]) or "none", f"`{v['run']}`"]
             for v in verdicts]
    return [*out, "", "## The imagined verdict on each suite's SFT policy (paired replay)", "",
            "Its imagined rollouts' actions replayed in the real simulator from the same start: imagined against real "
            "success of the same actions, and the share of imagined successes that fail for real (hack rate; the "
            "fidelity target <= 10 %). Closed-loop: the same policy's real success from the same contexts.", "",
            *markdown_table(["suite", "policy", "contexts", "imagined rollouts", "imagined success",
                             "real success, same actions", "hack rate", "real closed-loop success", "limits that hold",
                             "kept run"], vrows)]


def write_kept(spec_path: str | Path, out: str | Path | None = None) -> Path:
    """<out>/suites.{md,json} (out: the spec's folder) from the kept evaluations the spec names."""
    spec_path = Path(spec_path)
    out = Path(out) if out else spec_path.parent
    rows, verdicts = kept_rows(spec_path)
    write_text_atomic(out / "suites.json", json.dumps({"rows": rows, "verdicts": verdicts}, indent=1))
    path = out / "suites.md"
    write_text_atomic(path, "\n".join([
        "# SFT against post-trained, per suite, from the kept evaluations", "",
        f"Generated by `python -m stages.suites --kept {spec_path.parent.name}/{spec_path.name}` (`make suites-table`) from the "
        "evaluations kept under `results/` (each episode's outcome), paired by (task, init state) with the exact "
        "McNemar test; edit the spec, not this file. Oracle termination unless a column says otherwise.", "",
        *kept_table(rows, verdicts)]) + "\n")
    return path


USAGE = ("usage: python -m stages.suites <out_dir> <task>=<experiment_dir> [...]\n"
         "       python -m stages.suites --kept <spec.yaml> [<out_dir>]")


def main(argv: list[str]) -> None:
    if argv[:1] == ["--kept"] and len(argv) in (2, 3):
        print(write_kept(*argv[1:]))
        return
    if len(argv) < 2 or not all("=" in a for a in argv[1:]):
        raise SystemExit(USAGE)
    print(write(argv[0], dict(a.split("=", 1) for a in argv[1:])))


if __name__ == "__main__":
    with user_errors():
        main(sys.argv[1:])
