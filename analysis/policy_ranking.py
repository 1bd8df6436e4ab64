"""The world model as a policy ranker, checked against real evaluations already kept: each paired policy
of one `evaluate_imagination` run, its imagined success (by the run's reflector and by each further
reflector) against its success in the `evaluate` runs of the same checkpoint (e.g. 300 episodes from the
benchmark's init states), with the rank correlation and a 95 % bootstrap interval over contexts and
episodes. The real success of the imagined actions themselves (the pairs) is ranked against the
evaluations too: how far the run's contexts can rank policies at all, whatever imagination says.

    python -m analysis.policy_ranking results/libero_goal/evaluate_imagination-<id> \\
        --real results/libero_goal/evaluate-24436df546de results/libero_goal/evaluate-6bc9ec720a68 ...
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from worldenv_core.evaluations import checkpoint_name
from worldenv_core.evaluations import pooled_episodes, read_evaluation
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.imagination.verdict import as_judged_by, context_key, judge, misattributed
from worldenv_core.stats import spearman
from worldenv_core.viz import figure, save_figure


def real_skill(folders: list[str]) -> dict[str, dict[tuple[int, int], bool]]:
    """{checkpoint name: {(task, init state): success}}, the evaluations of one checkpoint pooled."""
    by_policy = defaultdict(list)
    for f in folders:
        summary, _ = read_evaluation(None, f)
        by_policy[checkpoint_name(summary["policy"])].append(f)
    return {name: pooled_episodes(None, fs)[0] for name, fs in by_policy.items()}


def imagined_skill(folder: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """{reflector: {checkpoint name: [contexts, 2] imagined and real success of the pairs, the mean over
    each context's rollouts}}: the paired policies at noise 1, judged as the run judged them."""
    summary = json.loads((Path(folder) / "fidelity.json").read_text())
    pairs = json.loads((Path(folder) / "pairs.json").read_text())
    judges = {"headline": (None, summary["eta"])} | {n: (n, j["eta"]) for n, j in summary.get("judges", {}).items()}
    out = {name: {} for name in judges}
    for variant, data in pairs.items():
        path, _, noise = variant.rpartition("@")
        if not data.get("rows") or float(noise) != 1.0:
            continue
        for name, (judge_name, eta) in judges.items():
            groups = defaultdict(list)
            for row, void in zip(data["rows"], misattributed(data["rows"])):
                if void:  # its real side is another context's
                    continue
                j = judge(as_judged_by(row, judge_name) if judge_name else row, eta)
                groups[context_key({**row, "policy": None})].append((j["imagined_success"], j["real_success"]))
            out[name][checkpoint_name(path)] = {k: np.mean(v, axis=0) for k, v in groups.items()}
    return out


def ranking(folder: str | Path, real_folders: list[str], draws: int = 2000, seed: int = 0) -> dict:
    real = real_skill(real_folders)
    out = {}
    for reflector, per_policy in imagined_skill(folder).items():
        names = sorted(set(per_policy) & set(real))
        if len(names) < 3:
            raise ConfigError(f"{len(names)} policies are both paired in {folder} and evaluated in --real "
                              f"({sorted(per_policy)} against {sorted(real)}): a ranking needs 3 or more")
        contexts = sorted(set.intersection(*[set(per_policy[n]) for n in names]), key=str)
        episodes = sorted(set.intersection(*[set(real[n]) for n in names]))
        # [policies, contexts, (imagined, real of the pairs)] and [policies, episodes]
        paired = np.array([[per_policy[n][c] for c in contexts] for n in names], dtype=float)
        evaluated = np.array([[real[n][e] for e in episodes] for n in names], dtype=float)
        rng = np.random.default_rng(seed)
        boot = []
        for _ in range(draws):  # the same contexts and episodes for every policy: a paired bootstrap
            p = paired[:, rng.integers(0, len(contexts), len(contexts))].mean(axis=1)
            e = evaluated[:, rng.integers(0, len(episodes), len(episodes))].mean(axis=1)
            boot.append((spearman(p[:, 0], e), spearman(p[:, 1], e), spearman(p[:, 0], p[:, 1])))
        boot = np.array(boot)
        means, ev = paired.mean(axis=1), evaluated.mean(axis=1)
        figures = {"imagined_vs_evaluation": spearman(means[:, 0], ev), "pairs_vs_evaluation": spearman(means[:, 1], ev),
                   "imagined_vs_pairs": spearman(means[:, 0], means[:, 1])}
        out[reflector] = {
            "policies": {n: {"imagined_success": float(means[i, 0]), "pairs_real_success": float(means[i, 1]),
                             "evaluation_success": float(ev[i])} for i, n in enumerate(names)},
            "contexts": len(contexts), "episodes": len(episodes),
            **{k: {"spearman": v, "ci95": _interval(boot[:, i])} for i, (k, v) in enumerate(figures.items())}}
    return out


def _interval(draws: np.ndarray) -> list[float]:
    """The 95 % interval of the draws where the correlation is defined (a draw with one side all
    equal has none)."""
    draws = draws[~np.isnan(draws)]
    return [float(x) for x in np.percentile(draws, [2.5, 97.5])] if len(draws) else [float("nan")] * 2


WHO = {"headline": "the run's reflector"}


def plot_ranking(out: dict, path: str | Path) -> Path:
    """Per reflector, each policy's imagined success (and the real success of its imagined actions)
    against its evaluation: a ranker puts the points in the evaluation's order, not on the diagonal
    (the run's contexts are not the evaluation's)."""
    fig, axes = figure(1, len(out), figsize=(4.2 * len(out), 4), squeeze=False)
    for ax, (reflector, r) in zip(axes[0], out.items()):
        ms = r["policies"]
        ev = [m["evaluation_success"] for m in ms.values()]
        ax.scatter(ev, [m["imagined_success"] for m in ms.values()], marker="o", label="imagined")
        ax.scatter(ev, [m["pairs_real_success"] for m in ms.values()], marker="x", label="real, same actions")
        for name, m in ms.items():
            ax.annotate(name.removesuffix("/policy").split("/")[-1], (m["evaluation_success"], m["imagined_success"]), fontsize=6)
        rho = r["imagined_vs_evaluation"]
        ax.set(xlabel="real success in the evaluations", ylabel="success on the run's contexts", ylim=(-0.02, 1.02),
               title=f"{WHO.get(reflector, reflector)}: Spearman {rho['spearman']:.2f} [{rho['ci95'][0]:.2f}, {rho['ci95'][1]:.2f}]")
        ax.title.set_fontsize(8)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="an evaluate_imagination output folder (fidelity.json, pairs.json)")
    p.add_argument("--real", nargs="+", required=True, help="evaluate output folders (results.json, episodes.json)")
    p.add_argument("--json", help="also write the figures here")
    p.add_argument("--plot", help="and the plot (png) here")
    args = p.parse_args(argv)
    out = ranking(args.run, args.real)
    for reflector, r in out.items():
        print(f"{reflector}: {r['contexts']} contexts, {r['episodes']} real episodes a policy")
        for name, m in sorted(r["policies"].items(), key=lambda kv: -kv[1]["evaluation_success"]):
            print(f"  {name:40s} imagined {m['imagined_success']:.3f}  pairs real {m['pairs_real_success']:.3f}  "
                  f"evaluation {m['evaluation_success']:.3f}")
        for k in ("imagined_vs_evaluation", "pairs_vs_evaluation", "imagined_vs_pairs"):
            print(f"  Spearman {k}: {r[k]['spearman']:.2f} [{r[k]['ci95'][0]:.2f}, {r[k]['ci95'][1]:.2f}]")
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(out, indent=1) + "\n")
    if args.plot:
        plot_ranking(out, args.plot)
    return out


if __name__ == "__main__":
    with user_errors():
        main()
