"""The policy a kept ES ledger describes: the starting policy moved by the ledger's first `--upto` iterations.

A weight-space run (`rl=es`) keeps, per iteration, its contexts, direction seeds and outcomes
(`<work>/es_ledger/`, exported into `results/rl_recipes/`): with the starting policy that is all its weights
follow from (`worldenv_core.rl.es.replay_ledger`). This writes that policy as a checkpoint folder, so a kept
campaign's policy at any iteration is evaluated, compared or used as a control's `--like` on a machine whose
`outputs/` never held the run.

    python -m analysis.ledger_policy --policy checkpoints/libero_spatial/sft \\
        --ledger results/rl_recipes/es_task4_seed0_ledger --upto 2 --out outputs/libero_spatial-small/es_task4_iter2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import load_checkpoint, read_config, save_model
from worldenv_core.rl import es


def ledger_entries(ledger: str | Path, upto: int | None = None) -> tuple[list[dict], int]:
    """A kept ledger's entries and how many of them to replay (all by default), or a one-line error naming
    the folder. -> (entries, upto)"""
    try:
        entries = es.read_ledger(ledger)
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(f"--ledger {ledger}: {e}") from None
    if not entries:
        raise ConfigError(f"--ledger {ledger} holds no iter_NNNN.json")
    upto = len(entries) if upto is None else upto
    if not 0 <= upto <= len(entries):
        raise ConfigError(f"--upto {upto}: the ledger {ledger} holds iterations 1..{len(entries)}")
    return entries, upto


def ledger_policy(policy: str | Path, ledger: str | Path, out: str | Path, upto: int | None = None) -> Path:
    """`policy` moved by `ledger`'s iterations 1..`upto` (all by default), saved at `out`. -> `out`"""
    entries, upto = ledger_entries(ledger, upto)
    model, _ = load_checkpoint(policy, "policy")
    try:
        es.check_start(ledger, es.weights_digest(model))
    except ValueError as e:
        raise ConfigError(f"--ledger {ledger} with --policy {policy}: {e}") from None
    es.replay_ledger(model, entries, upto)
    config = read_config(policy)
    meta = {**config.get("meta", {}), "es_ledger": Path(ledger).name, "es_iterations": upto}
    return save_model(out, model, config["model"], meta)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help="the run's starting policy (a checkpoint folder)")
    p.add_argument("--ledger", required=True, help="a folder of iter_NNNN.json (an exported es_ledger)")
    p.add_argument("--upto", type=int, default=None, help="iterations to replay (default: all the ledger holds)")
    p.add_argument("--out", required=True, help="the checkpoint folder to write")
    args = p.parse_args(argv)
    with user_errors():
        print(ledger_policy(args.policy, args.ledger, args.out, args.upto))


if __name__ == "__main__":
    main(sys.argv[1:])
