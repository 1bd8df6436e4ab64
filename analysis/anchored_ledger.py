"""A kept ES ledger replayed with each step anchored: its effect kept on the tasks it was measured on and pulled
back on the others' recorded frames (`worldenv_core.rl.anchor`).

A one-task-per-iteration run (`rl=es_by_task`, `es_many_pairs`) measures each step on one task and applies it to
the whole policy. Replaying its ledger with every step anchored asks, without a real episode, whether the trades
between tasks come from those steps' effects off their task: the anchored policy is then judged on the runs'
validation set (`analysis.validation`) beside the ledger's own. The later iterations' returns were measured along
the run's own path, so this is the anchored recipe to first order, as `analysis.random_update --along` is a longer
step. An iteration's task is its contexts' (fresh placement k is of the task at position k mod `--n-tasks`).

    python -m analysis.anchored_ledger --policy checkpoints/libero_spatial/sft \\
        --ledger results/rl_recipes/es_by_task_seed0_ledger --frames "data/libero_spatial/expert-*/task*/*.mcap" \\
        --out outputs/libero_spatial-small/es_by_task_seed0_anchored --json results/rl_recipes/anchored_es_by_task.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def own_tasks(contexts: list[int], n_tasks: int) -> set[int]:
    """The tasks an iteration's fresh placements are of."""
    return {int(c) % n_tasks for c in contexts}


def anchored_replay(policy: torch.nn.Module, entries: list[dict], frames, n_tasks: int, upto: int | None = None,
                    iterations: int = 200, lr: float = 1e-4, batch: int = 128, log=print) -> list[dict]:
    """`policy` moved in place by the ledger's steps 1..`upto`, each anchored. -> each step's figures."""
    from worldenv_core.rl import es
    from worldenv_core.rl.anchor import anchored_step

    out = []
    for e in entries[:upto]:
        if e.get("rolled_back") or e.get("no_step"):
            continue
        tasks = own_tasks(e["contexts"], n_tasks)
        t0 = time.perf_counter()
        stats = anchored_step(policy, lambda p: es.ars_update(p, e["seeds"], torch.tensor(e["returns"]), e["es_step"],
                                                              e["es_top"], e["es_parameters"]),
                              frames, tasks, e["es_parameters"], iterations, lr, batch, seed=int(e["iteration"]))
        stats.update({"iteration": int(e["iteration"]), "tasks": sorted(tasks), "seconds": time.perf_counter() - t0})
        log(f"iteration {stats['iteration']} (tasks {stats['tasks']}): actions moved {stats['anchor_moved_own']:.4f} "
            f"on its tasks' frames, {stats['anchor_moved_other']:.4f} on the others'; anchored: "
            f"{stats['anchor_left_other']:.2f} of it left on the others, own error {stats['anchor_own_error']:.2f} "
            f"({stats['seconds']:.0f} s)")
        out.append(stats)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help="the run's starting policy (a checkpoint folder)")
    p.add_argument("--ledger", required=True, help="a folder of iter_NNNN.json (an exported es_ledger)")
    p.add_argument("--frames", nargs="+", required=True, help="recorded episodes of the suite's tasks (files, folders, globs)")
    p.add_argument("--out", required=True, help="the checkpoint folder to write")
    p.add_argument("--upto", type=int, default=None, help="iterations to replay (default: all)")
    p.add_argument("--n-tasks", type=int, default=10, help="the tasks the run trained on")
    p.add_argument("--iterations", type=int, default=200, help="anchoring steps per ES step")
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--every", type=int, default=8, help="every n-th recorded frame (the policy reads one a chunk)")
    p.add_argument("--json", type=Path, help="write each step's figures here")
    args = p.parse_args(argv)
    with user_errors():
        from worldenv_core.data.selection import expand_episode_paths
        from worldenv_core.models.checkpoint import load_checkpoint, read_config, save_model
        from worldenv_core.models.text import InstructionEncoder
        from worldenv_core.rl import es
        from worldenv_core.rl.anchor import anchor_frames

        try:
            entries = es.read_ledger(args.ledger)
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"--ledger {args.ledger}: {e}") from None
        if not entries:
            raise ConfigError(f"--ledger {args.ledger} holds no iter_NNNN.json")
        upto = len(entries) if args.upto is None else args.upto
        if not 0 <= upto <= len(entries):
            raise ConfigError(f"--upto {upto}: the ledger {args.ledger} holds iterations 1..{len(entries)}")
        files = expand_episode_paths(args.frames)
        if not files:
            raise ConfigError(f"--frames {' '.join(args.frames)}: no recorded episode there")
        model, _ = load_checkpoint(args.policy, "policy")
        frames = anchor_frames(files, model.cameras, InstructionEncoder(), args.every)
        missing = sorted(set(range(args.n_tasks)) - set(frames.task_ids.tolist()))
        if missing:
            raise ConfigError(f"--frames: no recorded episode of task(s) {missing}: their actions cannot be anchored")
        print(f"{len(frames)} frames of {len(files)} episodes")
        steps = anchored_replay(model, entries, frames, args.n_tasks, upto, args.iterations, args.lr, args.batch)
        config = read_config(args.policy)
        meta = {**config.get("meta", {}), "es_ledger": Path(args.ledger).name, "es_iterations": upto,
                "anchored": {"iterations": args.iterations, "lr": args.lr, "batch": args.batch, "frames": len(frames)}}
        print(save_model(args.out, model, config["model"], meta))
        if args.json:
            write_text_atomic(args.json, json.dumps({"ledger": Path(args.ledger).name, "upto": upto, "steps": steps},
                                                    indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
