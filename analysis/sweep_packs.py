"""The sweep summary (`stages.post_train_loop.sweep.write_summary`) of a sweep run from a context
pack on a GPU host (`python -m stages.post_train_loop -m contexts_from=<pack> eta=... rl.n_rollouts=...`,
one work dir per point, fetched back), measured back where the simulator is: each point's real
success from the experiment's `evaluate` records of its policy, paired with the starting policy's
evaluation on the same episodes (McNemar), and its paired hack rate from the `evaluate_imagination`
record that replayed it at its eta (the starting policy's from the same record).

    python -m analysis.sweep_packs outputs/libero_object-small --packs <work dirs> \\
        --baseline results/libero_object/evaluate-329fcc83d07b --out <folder>
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from worldenv_core.evaluations import compare, pooled_episodes
from stages.evaluate_imagination.run import pairs_key
from stages.post_train_loop.sweep import write_summary
from worldenv_core.imagination.verdict import verdict_metrics
from worldenv_core.manifest import Manifest, sha256_file
from worldenv_core.models.checkpoint import WEIGHTS, read_config


def pack_rows(manifest: Manifest, packs: list[Path], baseline: list[str]) -> list[dict]:
    """Summary rows of post_train_loop work dirs trained from a context pack, one per point of a sweep, measured in `manifest`'s
    experiment. `baseline`: the starting policy's evaluation (record ids or kept folders, pooled)."""
    base, _ = pooled_episodes(manifest, baseline)
    records = manifest.records()
    weights_of = {}  # an evaluated policy folder -> its weights' hash (each file read once)

    def weights(folder) -> str | None:
        if folder not in weights_of:
            f = Path(folder) / WEIGHTS
            weights_of[folder] = sha256_file(f) if f.is_file() else None
        return weights_of[folder]

    # the oracle evaluations other than the baseline's, by the policy folder each evaluated
    oracle = [(r.id, r.metrics["policy"], Path(r.metrics["policy"]).resolve()) for r in records
              if r.stage == "evaluate" and r.metrics.get("termination") == "oracle" and "policy" in r.metrics
              and r.id not in baseline]
    rows = []
    for work in packs:
        work = Path(work)
        meta = read_config(work / "policy")["meta"]
        n_rollouts = json.loads((work / "run_config.json").read_text())["rl"]["n_rollouts"]
        eta, own = meta["trained_from"]["eta"], weights(str(work / "policy"))
        # real success: every oracle evaluation of this folder, pooled (else of a copy of its weights elsewhere),
        # against the baseline on the same episodes
        here = (work / "policy").resolve()
        evals = [rid for rid, _, resolved in oracle if resolved == here]
        evals = evals or [rid for rid, policy, _ in oracle if weights(policy) == own][-1:]
        real = compare(base, pooled_episodes(manifest, evals)[0]) if evals else None
        history = json.loads((work / "training.json").read_text())
        imagined = [h for h in history if "imagined_reward" in h]
        trained = [h for h in history if "kept_groups" in h]
        start = weights(meta["post_trained_from"])
        hack_first, hack_last, replays = _hack_rates(manifest, records, eta, start, own)
        rows.append({"eta": eta, "n_rollouts": int(n_rollouts), "run": work.name, "iterations": meta["iteration"],
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
    def rows_of(work: Path, weights_hash: str):
        f = work / f"{pairs_key(weights_hash)}.json"
        return json.loads(f.read_text())["rows"] if f.is_file() else None

    for rec in reversed(records):
        if rec.stage != "evaluate_imagination" or rec.metrics.get("eta") != eta:
            continue
        fidelity = [a.path for a in rec.files("report") if Path(a.path).name == "fidelity.json"]
        if not fidelity:
            continue
        work = manifest.root / Path(fidelity[0]).parent  # the run's work dir: its pairs files
        first, last = rows_of(work, start), rows_of(work, own)
        if first and last:
            return (verdict_metrics(first, eta).get("hack_rate"), verdict_metrics(last, eta).get("hack_rate"), [rec.id])
    return None, None, []


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description="The summary of a sweep run from a context pack (see the module's doc)")
    p.add_argument("experiment_dir", help="where the points' evaluate and evaluate_imagination records are")
    p.add_argument("--packs", nargs="+", required=True, help="the post_train_loop work dirs, one per point")
    p.add_argument("--baseline", nargs="+", required=True, help="the starting policy's oracle evaluation(s)")
    p.add_argument("--out", required=True, help="folder for sweep_summary.{json,md,png}")
    args = p.parse_args(argv)
    rows = pack_rows(Manifest(args.experiment_dir), [Path(x) for x in args.packs], args.baseline)
    path = write_summary(Path(args.out), rows=rows)
    print((Path(args.out) / "sweep_summary.md").read_text(), end="")
    return path


if __name__ == "__main__":
    main()
