"""Is one policy the odd one out among several evaluated on the same episodes?

`paired` tests two policies. When several updates of one start (a post-trained policy, its controls)
all sit above it, each paired test is weak alone; this asks whether the *start* is the odd one. On
the episodes every policy ran, the policies are taken as exchangeable under the null hypothesis:
which of them got which of an episode's outcomes is chance, so the first policy succeeds there with
probability (successes among them) / (policies). Its success count is then a sum of independent
Bernoullis (Poisson-binomial), computed exactly; the p-value is how far out the observed count lies.
Each side pools evaluations as `paired` does (record ids or kept folders).

    python -m analysis.odd_one_out - --first results/libero_spatial/evaluate-{A,B} \\
        --other results/libero_spatial/evaluate-C --other results/libero_spatial/evaluate-D [--json F]
"""

from __future__ import annotations

import argparse

import numpy as np

from worldenv_core.evaluations import emit, pooled_policies
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.report import markdown_table


def poisson_binomial(p: np.ndarray) -> np.ndarray:
    """P(sum = j) for j = 0..len(p), the sum of independent Bernoulli(p_i)."""
    dist = np.zeros(len(p) + 1)
    dist[0] = 1.0
    for i, q in enumerate(p):
        dist[1:i + 2] = dist[1:i + 2] * (1 - q) + dist[:i + 1] * q
        dist[0] *= 1 - q
    return dist


def odd_one_out(first: dict, others: list[dict]) -> dict:
    """The test over the episodes all policies ran. `first`, `others`: {(task, init state): success}."""
    if not others:
        raise ConfigError("give at least one other policy")
    keys = sorted(set(first).intersection(*others))
    if not keys:
        raise ConfigError("the policies share no episode (task, init state)")
    outcomes = np.array([[first[k], *(o[k] for o in others)] for k in keys], dtype=float)
    chance = outcomes.mean(axis=1)  # the first's success probability on each episode under exchangeability
    dist = poisson_binomial(chance)
    observed = int(outcomes[:, 0].sum())
    lower, upper = float(dist[:observed + 1].sum()), float(dist[observed:].sum())
    solved, policies = outcomes.sum(axis=1), outcomes.shape[1]
    alone_fails = ((outcomes == 0) & (solved == policies - 1)[:, None]).sum(axis=0)
    alone_succeeds = ((outcomes == 1) & (solved == 1)[:, None]).sum(axis=0)
    return {"episodes": len(keys), "success": outcomes.mean(axis=0).tolist(), "first_successes": observed,
            "expected": float(chance.sum()), "p_lower": min(1.0, lower), "p_upper": min(1.0, upper),
            "p_value": min(1.0, 2 * min(lower, upper)), "alone_fails": alone_fails.tolist(),
            "alone_succeeds": alone_succeeds.tolist(), "episodes_that_differ": int(((solved > 0) & (solved < policies)).sum())}


def markdown(result: dict, names: list[str]) -> str:
    rows = [[("**" + n + "** (first)") if i == 0 else n, f"{100 * s:.1f} %", result["alone_fails"][i],
             result["alone_succeeds"][i]] for i, (n, s) in enumerate(zip(names, result["success"]))]
    head = ["policy", "success", "episodes it alone fails", "episodes it alone solves"]
    return "\n".join([*markdown_table(head, rows), "",
                      f"over {result['episodes']} episodes all ran ({result['episodes_that_differ']} where they differ): "
                      f"the first solves {result['first_successes']}, {result['expected']:.1f} expected if the "
                      f"policies were exchangeable; exact p = {result['p_value']:.3g} (two-sided; "
                      f"{result['p_lower']:.3g} that it is this low or lower)"]) + "\n"


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--first", nargs="+", required=True, help="evaluations of the policy tested (pooled)")
    p.add_argument("--other", nargs="+", action="append", required=True,
                   help="evaluations of another policy (pooled); repeat for each")
    p.add_argument("--json", help="also write the result here")
    args = p.parse_args(argv)
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    sides = pooled_policies(manifest, [args.first, *args.other])
    result = odd_one_out(sides[0][0], [episodes for episodes, _ in sides[1:]])
    names = [setting["policy"] for _, setting in sides]
    result.update(policies=names, records=[args.first, *args.other], termination=sides[0][1]["termination"],
                  suite=sides[0][1]["suite"])
    return emit(result, markdown(result, names), args.json)


if __name__ == "__main__":
    with user_errors():
        main()
