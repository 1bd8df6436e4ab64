"""Two policies on the real episodes both ran, pooled over evaluation records: success of each,
per task and overall, the episodes only one of them solved, and the exact McNemar p-value.
Several evaluations per side pool their episodes, so a benchmark evaluated in ranges
(`init_states=20`, then `first_init_state=20 init_states=30`) compares as one 500-episode run.
An evaluation is named by its manifest record id or by its output folder (`results.json` and
`episodes.json`, as `evaluate` writes them and as kept under `results/` in the repository).

    python -m analysis.paired outputs/libero_goal-small \\
        --a evaluate-05f27e1f2f64 evaluate-b3f4f4885ad3 --b evaluate-e20e05a3d33f [--json paired.json]
    python -m analysis.paired - --a results/libero_goal/evaluate-* --b <work>/evaluate/...
"""

from __future__ import annotations

import argparse

from worldenv_core.errors import ConfigError
from worldenv_core.evaluations import compare, emit, paired_markdown, pooled_episodes
from worldenv_core.manifest import Manifest


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment_dir", help="where record ids are looked up ('-': only output folders are named)")
    p.add_argument("--a", nargs="+", required=True, help="evaluations of the first policy (pooled)")
    p.add_argument("--b", nargs="+", required=True, help="evaluations of the second policy (pooled)")
    p.add_argument("--json", help="also write the result here")
    args = p.parse_args(argv)
    manifest = None if args.experiment_dir == "-" else Manifest(args.experiment_dir)
    (a, a_setting), (b, b_setting) = pooled_episodes(manifest, args.a), pooled_episodes(manifest, args.b)
    for what in ("termination", "suite"):
        if a_setting[what] != b_setting[what]:
            raise ConfigError(f"the sides ran {what} {a_setting[what]!r} and {b_setting[what]!r}: not the same episodes")
    result = compare(a, b)
    result.update(a_records=args.a, b_records=args.b, a_policy=a_setting["policy"], b_policy=b_setting["policy"],
                  termination=a_setting["termination"], suite=a_setting["suite"])
    return emit(result, paired_markdown(result, a_setting["policy"], b_setting["policy"]), args.json)


if __name__ == "__main__":
    main()
