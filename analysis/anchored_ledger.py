"""A kept ES ledger replayed with each step anchored: its effect kept on the tasks it was measured on and pulled
back on the others' recorded frames (`anchored_step`).

A one-task-per-iteration run (`rl=es_by_task`, `es_many_pairs`) measures each step on one task and applies it to
the whole policy. Replaying its ledger with every step anchored asks, without a real episode, whether the trades
between tasks come from those steps' effects off their task: the anchored policy is then judged on the runs'
validation set (`analysis.validation`) beside the ledger's own. The later iterations' returns were measured along
the run's own path, so this is the anchored recipe to first order, as `analysis.random_update --along` is a longer
step. An iteration's task is its contexts' (fresh placement k is of the task at position k mod `--n-tasks`).

Anchoring: after the step, a few Adam steps on the parameters ES moves pull the mean action chunks on recorded
frames (the demos) of the tasks the step was not measured on back to their values before it, and hold those of its
own tasks where it took them. Measured on `es_by_task`'s 20 steps (libero_spatial; docs/notebook/rl_recipe.md,
session 2026-12-04 (5)): each step moves the other tasks' actions as much as its own (median 0.047 against
0.046 RMS), anchoring leaves a median 0.22 of that on them (own error 0.25), and the anchored policy validates at 0.63 against the
plain replay's 0.70 (SFT 0.56), task 4 back at SFT's 10 %: the steps off their task carried gains as well as trades.

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
from typing import Callable

import torch

from analysis.ledger_policy import ledger_entries
from analysis.policy_frames import PolicyFrames, mean_actions, policy_frames
from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.rl import es


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt()) if x.numel() else float("nan")


def anchored_step(policy: torch.nn.Module, step: Callable[[torch.nn.Module], dict], frames: PolicyFrames,
                  own_tasks, which: str = "mean", iterations: int = 200, lr: float = 1e-4, batch: int = 128,
                  seed: int = 0) -> dict:
    """`step(policy)` (in place), then `iterations` Adam steps on the parameters ES moves (`which`) pulling the
    mean actions on frames of tasks outside `own_tasks` back to their values before the step and holding those of
    `own_tasks` at their values after it. -> the step's figures with how much of its action change on each side
    is left (`anchor_left_other`: near 0 removes it from the others) and how far the own tasks' actions ended from
    where the step took them (`anchor_own_error`, relative to the step's own change: near 0 keeps its effect)."""
    own = torch.isin(frames.task_ids, torch.as_tensor(sorted(set(int(t) for t in own_tasks)), dtype=torch.int64))
    was_training = policy.training
    policy.eval()
    before = mean_actions(policy, frames)
    stats = dict(step(policy))
    after = mean_actions(policy, frames)
    target = torch.where(own[:, None, None], after, before)
    moved_own, moved_other = _rms((after - before)[own]), _rms((after - before)[~own])
    params = [p for _, p in es.es_parameters(policy, which)]
    if (~own).any() and iterations > 0:
        opt = torch.optim.Adam(params, lr=lr)
        g = torch.Generator().manual_seed(seed)
        for _ in range(iterations):
            idx = torch.randint(len(frames), (min(batch, len(frames)),), generator=g)
            loss = (policy(*frames.rows(idx))[0] - target[idx]).pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        for p in policy.parameters():
            p.grad = None
    final = mean_actions(policy, frames)
    policy.train(was_training)
    return {**stats, "anchor_moved_own": moved_own, "anchor_moved_other": moved_other,
            "anchor_left_other": _rms((final - before)[~own]) / moved_other if moved_other else float("nan"),
            "anchor_own_error": _rms((final - after)[own]) / moved_own if moved_own else float("nan")}


def own_tasks(contexts: list[int], n_tasks: int) -> set[int]:
    """The tasks an iteration's fresh placements are of."""
    return {int(c) % n_tasks for c in contexts}


def anchored_replay(policy: torch.nn.Module, entries: list[dict], frames, n_tasks: int, upto: int | None = None,
                    iterations: int = 200, lr: float = 1e-4, batch: int = 128, log=print) -> list[dict]:
    """`policy` moved in place by the ledger's steps 1..`upto`, each anchored. -> each step's figures."""
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

        entries, upto = ledger_entries(args.ledger, args.upto)
        files = expand_episode_paths(args.frames)
        if not files:
            raise ConfigError(f"--frames {' '.join(args.frames)}: no recorded episode there")
        model, _ = load_checkpoint(args.policy, "policy")
        frames = policy_frames(files, model.cameras, InstructionEncoder(), args.every)
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
