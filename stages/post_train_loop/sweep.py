"""A Hydra sweep over eta and N (`python -m stages.post_train_loop -m eta=0.3,0.5,0.7
rl.n_rollouts=4,8`), summarised: each run of a sweep is tagged with its multirun folder, and the
summary (a table, and real success, imagined reward and hack rate against eta, one line per N)
is written into that folder after every run and drawn again in the experiment report.

The same summary for a sweep run as `from_pack` jobs (one work dir per point, on a GPU host),
measured back where the simulator is: each point's real success from the experiment's `evaluate`
records of its weights, paired with the starting policy's evaluation on the same episodes
(McNemar), and its paired hack rate from the `evaluate_imagination` records that replayed it at
its eta (the starting policy's from the same records):

    python -m stages.post_train_loop.sweep outputs/libero_object-small --packs <work dirs> \
        --baseline results/libero_object/evaluate-329fcc83d07b --out <folder>
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import Manifest, StageRecord, sha256_file
from worldenv_core.report import markdown_table
from worldenv_core.viz import figure, save_figure

# what a sweep compares: the record's metric (an {iteration: value} curve) and how it is named
MEASURES = (("real_success", "real success"), ("imagined_reward", "imagined reward"),
            ("paired_hack_rate", "paired hack rate"))


def sweep_dir() -> Path | None:
    """The multirun folder of this job when it runs in a Hydra sweep (`-m`), else None."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    return Path(HydraConfig.get().sweep.dir)


def _ends(curve: dict | None) -> tuple[float | None, float | None]:
    """(first, last) value of an {iteration: value} curve."""
    if not curve:
        return None, None
    steps = sorted(curve, key=int)
    return curve[steps[0]], curve[steps[-1]]


def summary_rows(runs: list[StageRecord]) -> list[dict]:
    """One row per point of the sweep, ordered by N then eta: each measure at the start (the SFT
    policy, iteration 0) and at the end."""
    newest = {(r.tags.get("eta"), r.tags.get("n_rollouts")): r for r in runs}  # a point re-run: its newest record
    rows = []
    for r in newest.values():
        row = {"eta": r.tags.get("eta"), "n_rollouts": r.tags.get("n_rollouts"), "run": r.id,
               "iterations": r.metrics.get("iterations"), "kept_groups": r.metrics.get("kept_groups")}
        for key, _ in MEASURES:
            row[f"{key}_first"], row[f"{key}_last"] = _ends(r.metrics.get(key))
        rows.append(row)
    return sorted(rows, key=lambda x: (x["n_rollouts"] or 0, x["eta"] if x["eta"] is not None else -1))


def _fmt(x, pct: bool = True) -> str:
    if x is None or (isinstance(x, float) and np.isnan(x)):
        return ""
    return f"{100 * x:.1f} %" if pct else f"{x:.3f}"


def summary_table(rows: list[dict]) -> list[str]:
    return markdown_table(
        ["eta", "N", "iterations", "real success (SFT -> last)", "imagined reward (SFT -> last)",
         "paired hack rate (SFT -> last)", "groups kept", "run"],
        [[r["eta"], r["n_rollouts"], r["iterations"],
          f"{_fmt(r['real_success_first'])} -> {_fmt(r['real_success_last'])}" + _paired(r),
          f"{_fmt(r['imagined_reward_first'], False)} -> {_fmt(r['imagined_reward_last'], False)}",
          f"{_fmt(r['paired_hack_rate_first'])} -> {_fmt(r['paired_hack_rate_last'])}",
          _fmt(r["kept_groups"]), f"`{r['run']}`"] for r in rows])


def _paired(row: dict) -> str:
    """A pack point's real comparison: the episodes only one side solved, and McNemar's p."""
    if row.get("real_p") is None:
        return ""
    return f" ({row['real_only_first']} / {row['real_only_last']}, p {row['real_p']:.2f}, {row['real_episodes']} eps)"


def plot_summary(rows: list[dict], path: Path) -> Path:
    """Each measure at the end of training against eta, one line per N (the SFT level dotted)."""
    fig, axes = figure(ncols=len(MEASURES), figsize=(4 * len(MEASURES), 3.3))
    for ax, (key, label) in zip(axes, MEASURES):
        for n in sorted({r["n_rollouts"] for r in rows}, key=lambda v: v or 0):
            got = [(r["eta"], r[f"{key}_last"]) for r in rows if r["n_rollouts"] == n and r[f"{key}_last"] is not None
                   and r["eta"] is not None]
            if got:
                ax.plot([e for e, _ in got], [v for _, v in got], "-o", ms=4, label=f"N={n}")
        base = [r[f"{key}_first"] for r in rows if r[f"{key}_first"] is not None]
        if base:
            ax.axhline(float(np.mean(base)), color="k", ls=":", lw=0.8, label="SFT")
        ax.set(xlabel="eta", title=label)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def write_summary(folder: Path, runs: list[StageRecord] | None = None, rows: list[dict] | None = None) -> Path:
    """sweep_summary.{json,md,png} in the multirun folder (rewritten as each run finishes), from the
    sweep's records or from rows made otherwise (`pack_rows`)."""
    rows = summary_rows(runs) if rows is None else rows
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in (("sweep_summary.json", json.dumps(rows, indent=1)),
                       ("sweep_summary.md", "\n".join(summary_table(rows)) + "\n")):
        write_text_atomic(folder / name, text)
    return plot_summary(rows, folder / "sweep_summary.png")


def pack_rows(manifest: Manifest, packs: list[Path], baseline: list[str]) -> list[dict]:
    """Summary rows of `from_pack` work dirs, one per point of a sweep, measured in `manifest`'s
    experiment. `baseline`: the starting policy's evaluation (record ids or kept folders, pooled)."""
    from stages.evaluate.paired import compare, pooled_episodes
    from worldenv_core.models.checkpoint import WEIGHTS, read_config
    from worldenv_core.stage import compose_config

    base, _ = pooled_episodes(manifest, baseline)
    records = manifest.records()
    weights_of = {}  # an evaluated policy folder -> its weights' hash (each file read once)

    def weights(folder) -> str | None:
        if folder not in weights_of:
            f = Path(folder) / WEIGHTS
            weights_of[folder] = sha256_file(f) if f.is_file() else None
        return weights_of[folder]

    rows = []
    for work in packs:
        work = Path(work)
        meta = read_config(work / "policy")["meta"]
        plan = json.loads((work / "plan.json").read_text())
        cfg = compose_config("post_train_loop", [f"+task={meta['task']}", *plan["overrides"]])
        eta, own = meta["trained_from"]["eta"], weights(str(work / "policy"))
        # real success: every oracle evaluation of this folder, pooled (else of a copy of its weights elsewhere),
        # against the baseline on the same episodes
        oracle = [r for r in records if r.stage == "evaluate" and r.metrics.get("termination") == "oracle"
                  and r.id not in baseline]
        evals = [r.id for r in oracle if Path(r.metrics.get("policy", "")).resolve() == (work / "policy").resolve()]
        evals = evals or [r.id for r in oracle if weights(r.metrics.get("policy", "")) == own][-1:]
        real = compare(base, pooled_episodes(manifest, evals)[0]) if evals else None
        history = json.loads((work / "history.json").read_text())
        imagined = [h for h in history if "imagined_reward" in h]
        trained = [h for h in json.loads((work / "training.json").read_text()) if "kept_groups" in h]
        start = weights(meta["post_trained_from"])
        hack_first, hack_last, replays = _hack_rates(manifest, records, eta, start, own)
        rows.append({"eta": eta, "n_rollouts": int(cfg.rl.n_rollouts), "run": work.name, "iterations": meta["iteration"],
                     "kept_groups": float(np.mean([h["kept_groups"] for h in trained])) if trained else None,
                     "real_success_first": real and real["a"], "real_success_last": real and real["b"],
                     "real_episodes": real and real["episodes"], "real_only_first": real and real["only_a"],
                     "real_only_last": real and real["only_b"], "real_p": real and real["p_value"],
                     "real_records": evals, "paired_records": replays,
                     "imagined_reward_first": imagined[0]["imagined_reward"] if imagined else None,
                     "imagined_reward_last": imagined[-1]["imagined_reward"] if imagined else None,
                     "paired_hack_rate_first": hack_first, "paired_hack_rate_last": hack_last})
    return sorted(rows, key=lambda x: (x["n_rollouts"], x["eta"]))


def _hack_rates(manifest: Manifest, records, eta: float, start: str, own: str):
    """(starting policy's, this policy's) paired hack rate from the newest evaluate_imagination record
    at this eta that replayed both (pairs files are named by weights), and that record's id."""
    from stages.evaluate_imagination.run import pairs_key
    from worldenv_core.imagination.verdict import verdict_metrics

    def rows_of(work: Path, weights_hash: str):
        f = work / f"{pairs_key(weights_hash)}.json"
        return json.loads(f.read_text())["rows"] if f.is_file() else None

    for rec in reversed(records):
        if rec.stage != "evaluate_imagination" or rec.metrics.get("eta") != eta:
            continue
        fidelity = [o.path for o in rec.outputs if o.path.endswith("fidelity.json")]
        if not fidelity:
            continue
        work = manifest.root / Path(fidelity[0]).parent  # the run's work dir: its pairs files
        first, last = rows_of(work, start), rows_of(work, own)
        if first and last:
            return (verdict_metrics(first, eta).get("hack_rate"), verdict_metrics(last, eta).get("hack_rate"), [rec.id])
    return None, None, []


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description="The summary of a sweep run as from_pack jobs (see the module's doc)")
    p.add_argument("experiment_dir", help="where the points' evaluate and evaluate_imagination records are")
    p.add_argument("--packs", nargs="+", required=True, help="the from_pack work dirs, one per point")
    p.add_argument("--baseline", nargs="+", required=True, help="the starting policy's oracle evaluation(s)")
    p.add_argument("--out", required=True, help="folder for sweep_summary.{json,md,png}")
    args = p.parse_args(argv)
    rows = pack_rows(Manifest(args.experiment_dir), [Path(x) for x in args.packs], args.baseline)
    path = write_summary(Path(args.out), rows=rows)
    print((Path(args.out) / "sweep_summary.md").read_text(), end="")
    return path


if __name__ == "__main__":
    main()
