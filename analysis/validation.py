"""Any policy's success on the RL runs' fixed validation set, outside a run.

A real-route run (`post_train_loop env=real eval.validation=N`) judges its recipe on N fresh placements of the
tasks it trains on, the same set in every run and never a benchmark init state (`envs.placements`). This puts a
policy that no run evaluated on the same set: a ledger's policy moved further along its own update
(`analysis.random_update --along --scale C`), a control, a policy from another machine. Results go into the
experiment's validation cache, the one the runs read, so a policy a run validated is read back, not run again.

    python -m analysis.validation +task=libero_spatial --policy outputs/libero_spatial-small/es_iter8_x2 \\
        --episodes 100 --workers 2 --json results/rl_recipes/validation_es_iter8_x2.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.stats import wilson


def summary_line(name: str, result: dict) -> str:
    n = int(round(result["validation_n"]))
    lo, hi = wilson(int(round(result["validation_success"] * n)), n)
    tasks = sorted((k for k in result if k.startswith("validation_task")), key=lambda k: int(k[len("validation_task"):]))
    per_task = " / ".join(f"{100 * result[k]:.0f}" for k in tasks)
    return (f"{name}: {result['validation_success']:.2f} (95 % {lo:.2f}-{hi:.2f}, {n} placements"
            f"{', cached' if result.get('validation_cached') else ''}); tasks {per_task} %")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", nargs="+", required=True, help="checkpoint folders")
    ap.add_argument("--episodes", type=int, default=100, help="the set's size (the runs' eval.validation)")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--no-cache", action="store_true", help="run every episode, even for a policy validated before")
    ap.add_argument("--json", type=Path, help="write {policy: result} here")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=..., scale=...)")
    args = ap.parse_args(argv)
    with user_errors():
        from stages.post_train_loop.evaluation import validation_success
        from worldenv_core.stage import compose_config, task_contract

        if args.episodes <= 0:
            raise ConfigError(f"--episodes must be > 0, got {args.episodes}")
        missing = [p for p in args.policy if not (Path(p) / "model.safetensors").exists()]
        if missing:
            raise ConfigError(f"--policy {missing[0]}: no model.safetensors there (a checkpoint folder is needed)")
        cfg = compose_config("post_train_loop", ["scale=small", *args.overrides])
        contract = task_contract(cfg)
        cache = None if args.no_cache else Path(cfg.experiment_dir) / "post_train_loop" / "validation_cache"
        out = {}
        for policy in args.policy:
            result = validation_success(policy, contract, args.episodes, args.workers, bool(cfg.progress), cache=cache)
            result["validation_n"] = float(args.episodes)
            out[policy] = result
            print(summary_line(policy, result))
        if args.json:
            write_text_atomic(args.json, json.dumps(out, indent=1))
        return out


if __name__ == "__main__":
    main()
