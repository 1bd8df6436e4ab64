"""Paired-replay runs pooled: the headline policy's pairs of several `evaluate_imagination` runs (e.g. the
same contexts with another `seed`: new rollouts) judged as one set, by the run's own reflector at its eta
and by every further reflector that judged all of them, with 95 % intervals over contexts. A run is
named by its output folder (`fidelity.json` and `pairs.json`, as the stage writes them and as kept under
`results/`).

    python -m analysis.pooled_verdicts results/libero_goal/evaluate_imagination-8a69c60e37e8 \\
        results/libero_goal/evaluate_imagination-5f94c0bd948b
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from stages.evaluate_imagination.evaluation import judged
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.verdict import as_judged_by, misattributed

FIGURES = ("rollouts", "imagined_success", "real_success", "auroc", "auroc_ci95", "f1", "f1_ci95", "precision",
           "recall", "hack_rate", "hack_rate_ci95", "hacks", "max_task_gap", "timing_error_median")


def all_of(row: dict, etas: dict[str | None, float]) -> dict:
    """The row as several reflectors judge it at once (None: the run's own): success at the first check
    where every one passes its own eta, a pessimistic ensemble (the reward-model-ensemble remedy for
    hacking). Scores become the smallest margin over the etas, so the verdict is at eta 0."""
    def margins(side: str) -> list[float]:
        per = [(as_judged_by(row, n) if n else row)[side] for n in etas]
        return [min(s[i] - eta for s, eta in zip(per, etas.values())) for i in range(min(map(len, per)))]
    return {**row, "imagined_scores": margins("imagined_scores"), "real_scores": margins("real_scores")}


def read_runs(folders: list[str | Path], all_policies: bool = False) -> tuple[list[tuple[dict, dict]], list[dict]]:
    """-> ([(fidelity.json, pairs.json) of each run], the rows of their headline policy's pairs, or of
    every paired policy's), without pairs whose real side is another context's (`misattributed`)."""
    runs = [(json.loads((Path(f) / "fidelity.json").read_text()), json.loads((Path(f) / "pairs.json").read_text()))
            for f in folders]
    rows = []
    for s, pairs in runs:
        for name, v in pairs.items():
            if all_policies or name == s["headline_policy"]:
                rows += [r for r, void in zip(v["rows"], misattributed(v["rows"])) if not void]
    return runs, rows


def judged_by(runs: list[tuple[dict, dict]], rows: list[dict], reflector: str | None = None) -> tuple[list[dict], float]:
    """-> (the rows as `reflector` judges them, its eta): a further reflector that judged every run, or
    (None) the runs' own reflector, whose etas must agree."""
    if reflector is not None:
        judges = set.intersection(*[set(s.get("judges", {})) for s, _ in runs])
        if reflector not in judges:
            raise ConfigError(f"{reflector} did not judge every run (all of them: {sorted(judges)})")
        return [as_judged_by(r, reflector) for r in rows], runs[0][0]["judges"][reflector]["eta"]
    etas = {s["eta"] for s, _ in runs}
    if len(etas) != 1:
        raise ConfigError(f"the runs judge at different etas {sorted(etas)}: pool runs of one reflector "
                          "(or one further reflector of them all: --reflector)")
    return rows, etas.pop()


def pooled(folders: list[str | Path], ensemble: bool = False, all_policies: bool = False,
           reflector: str | None = None) -> dict[str, dict]:
    """-> {reflector: verdict metrics over the pooled pairs}; the runs must share eta and headline reflector.
    `ensemble`: also every reflector at once (`all_of`). `all_policies`: every paired policy's pairs, not
    only the headline policy's. `reflector`: only that further reflector's verdict, which its own eta
    fixes, so runs whose own reflectors differ pool too."""
    runs, rows = read_runs(folders, all_policies)
    if reflector is not None:
        return {reflector: judged(*judged_by(runs, rows, reflector))}
    judges = set.intersection(*[set(s.get("judges", {})) for s, _ in runs])
    out = {"headline": judged(*judged_by(runs, rows))}
    for name in sorted(judges):
        out[name] = judged([as_judged_by(r, name) for r in rows], runs[0][0]["judges"][name]["eta"])
    if ensemble and judges:
        thresholds = {None: out["headline"]["eta"]} | {n: out[n]["eta"] for n in sorted(judges)}
        out["all of them"] = judged([all_of(r, thresholds) for r in rows], 0.0)
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="evaluate_imagination output folders")
    p.add_argument("--ensemble", action="store_true", help="also the reflectors at once: success where all pass")
    p.add_argument("--all-policies", action="store_true", help="every paired policy's pairs, not only the headline's")
    p.add_argument("--reflector", help="only this further reflector (named as in fidelity.json's judges)")
    args = p.parse_args(argv)
    out = pooled(args.runs, ensemble=args.ensemble, all_policies=args.all_policies, reflector=args.reflector)
    for name, m in out.items():
        print(f"{name} (eta {m['eta']}): " + ", ".join(f"{k} {m[k]}" for k in FIGURES if k in m))
    return out


if __name__ == "__main__":
    with user_errors():
        main()
