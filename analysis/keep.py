"""Keep evaluations in the repository, without machine paths, under `<into>/<record id>/`:

* an `evaluate` record: its `results.json` and `episodes.json` (every episode's outcome, a few tens
  of KB), so a later paired test (`analysis.paired - --a results/...`) needs neither the
  experiment nor a re-run of the baseline;
* an `evaluate_imagination` record: its `fidelity.json` and `pairs.json` (every pair's scores and
  outcomes), checked against the hashes the manifest recorded, so `analysis.pooled_verdicts`
  and a later re-judging read them from the repository.

    python -m analysis.keep outputs/release-goal evaluate-24436df546de ... --into results/libero_goal
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from worldenv_core.evaluations import checkpoint_name
from worldenv_core.evaluations import read_evaluation
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.manifest import Manifest, StageRecord

IMAGINATION_FILES = ("fidelity.json", "pairs.json")


def portable(path: str) -> str:
    """A checkpoint path as the repository knows it: relative to here when inside, else by name."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return checkpoint_name(path)


def portable_text(text: str) -> str:
    """Text with this checkout's absolute prefix removed: every path inside it becomes relative to it
    (the contexts' recordings under data/, checkpoints named by absolute path)."""
    return text.replace(str(Path.cwd().resolve()) + "/", "")


def keep(manifest: Manifest, record_id: str, into: Path) -> Path:
    rec = manifest.get(record_id)
    if rec.stage == "evaluate_imagination":
        return keep_imagination(manifest, rec, into)
    if rec.stage != "evaluate":
        raise ConfigError(f"{record_id} is a {rec.stage} record: only evaluate and evaluate_imagination records are kept")
    summary, rows = read_evaluation(manifest, record_id)
    if summary is None or rows is None:
        raise ConfigError(f"{record_id}'s results.json or episodes.json is gone from {manifest.root}")
    summary = {k: v for k, v in summary.items() if k != "report_dir"}
    summary.update(policy=portable(summary["policy"]), record=record_id)
    if summary.get("reflector"):
        summary["reflector"] = portable(summary["reflector"])
    out = into / record_id
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "results.json", json.dumps(summary, indent=1) + "\n")
    # one episode a line: small, and a diff shows which episodes changed
    write_text_atomic(out / "episodes.json", "[\n" + ",\n".join(json.dumps(r) for r in rows) + "\n]\n")
    return out


def keep_imagination(manifest: Manifest, rec: StageRecord, into: Path) -> Path:
    # resolve() checks each file against the hash the manifest recorded: a kept copy is what the run wrote
    files = {p.name: p for p in manifest.resolve(rec, kind="report")}
    missing = [n for n in IMAGINATION_FILES if n not in files]
    if missing:
        raise ConfigError(f"{rec.id} recorded no {', '.join(missing)}: not a paired-replay run to keep")
    summary = json.loads(portable_text(files["fidelity.json"].read_text()))
    summary["record"] = rec.id
    out = into / rec.id
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "fidelity.json", json.dumps(summary, indent=1) + "\n")
    write_text_atomic(out / "pairs.json", portable_text(files["pairs.json"].read_text()))
    return out


def main(argv: list[str] | None = None) -> list[Path]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir")
    p.add_argument("records", nargs="+", help="evaluate or evaluate_imagination record ids")
    p.add_argument("--into", required=True, help="the folder to keep them in, e.g. results/libero_goal")
    args = p.parse_args(argv)
    manifest = Manifest(args.experiment_dir)
    kept = [keep(manifest, r, Path(args.into)) for r in args.records]
    for path in kept:
        print(path)
    return kept


if __name__ == "__main__":
    with user_errors():
        main()
