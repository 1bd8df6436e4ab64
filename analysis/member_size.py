"""How large is an ES member's move, for a given policy? Two measures to choose `rl.es_sigma` by.

`--frames`: the mean action's RMS change (normalised action units) when the policy's weights move by sigma times
each tensor's RMS in a random direction (`es.perturb`, the members' move), on recorded frames, for each `--sigma`:
no physics, seconds. Two policies compared at the same sigma say whose actions a member moves further.

`--ledger`: the policy itself and members at each `--sigma` (`--pairs` antithetic pairs) on the very starts of a
kept real-route ES ledger's `--iterations` (its context numbers: fresh placements), for real (counted, printed):
whether members fail because of their move or because those starts are hard for the policy too.

    python -m analysis.member_size +task=libero_spatial --policy <ACT checkpoint> \\
        --frames "data/libero_spatial/expert-*/task*/expert_0000.mcap" --sigma 0.01 0.02 0.05
    python -m analysis.member_size +task=libero_spatial --policy <ACT checkpoint> \\
        --ledger results/rl_recipes/es_many_pairs_act_seed0_ledger --iterations 1 2 --sigma 0.01 0.02 --pairs 2
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import torch

from worldenv_core.cli import user_errors
from worldenv_core.data.mcap_io.read import glob_episode_files
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def action_change(policy, frames, sigmas: list[float], directions: int = 4, which: str = "mean") -> dict[float, float]:
    """sigma -> the mean over `directions` seeds of the RMS change of the mean actions on `frames`."""
    from analysis.policy_frames import mean_actions
    from worldenv_core.rl import es

    base = mean_actions(policy, frames)
    out = {}
    for s in sigmas:
        moved = [es.perturb(copy.deepcopy(policy).eval(), seed, s, which) for seed in range(directions)]
        out[s] = float(torch.stack([(mean_actions(m, frames) - base).pow(2).mean().sqrt() for m in moved]).mean())
    return out


def members(sigmas: list[float], pairs: int, seed: int = 0) -> list[tuple[int, float]]:
    """The policy itself (coefficient 0) first, then `pairs` antithetic pairs at each sigma, the same seeds for all."""
    from worldenv_core.rl import es

    seeds = torch.randint(2**62, (pairs,), generator=torch.Generator().manual_seed(seed)).tolist()
    return [(seeds[0], 0.0)] + [m for s in sigmas for m in es.antithetic_members(seeds, s)]


def by_member(success: torch.Tensor, sigmas: list[float], pairs: int) -> dict[str, list[int]]:
    """(starts, 1 + 2 pairs per sigma) outcomes -> {"policy": per start, "sigma <s>": per start successes}."""
    out = {"policy": success[:, 0].int().tolist()}
    for i, s in enumerate(sigmas):
        cols = slice(1 + 2 * pairs * i, 1 + 2 * pairs * (i + 1))
        out[f"sigma {s}"] = success[:, cols].int().sum(1).tolist()
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True, help="the policy (checkpoint folder)")
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--frames", nargs="+", help="recorded episodes (globs): the action change, no physics")
    source.add_argument("--ledger", type=Path, help="a kept real-route ES ledger: its starts, for real")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1], help="with --ledger: whose starts (from 1)")
    ap.add_argument("--sigma", type=float, nargs="+", required=True, help="the members' sizes (es_sigma units)")
    ap.add_argument("--pairs", type=int, default=2, help="with --ledger: antithetic pairs per sigma")
    ap.add_argument("--seed", type=int, default=0, help="with --ledger: the members' directions")
    ap.add_argument("--every", type=int, default=16, help="with --frames: every n-th frame of each episode")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--journal", type=Path, help="with --ledger: keep finished real rollouts here (resume)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=...)")
    args = ap.parse_args(argv)
    with user_errors():
        if any(not s > 0 for s in args.sigma) or args.pairs < 1:
            raise ConfigError(f"--sigma must be positive and --pairs >= 1, got {args.sigma} and {args.pairs}")
        from worldenv_core.models.checkpoint import load_checkpoint
        from worldenv_core.models.text import InstructionEncoder
        from worldenv_core.stage import compose_config, task_contract

        contract = task_contract(compose_config("post_train_loop", ["scale=small", *args.overrides]))
        if args.ledger:
            files = [args.ledger / f"iter_{i:04d}.json" for i in args.iterations]
            missing = [str(f) for f in files if not f.is_file()]
            if missing:
                raise ConfigError(f"--ledger {args.ledger}: no {', '.join(missing)}")
        policy, _ = load_checkpoint(args.policy, "policy", contract, device="cpu")
        policy.eval()
        encoder = InstructionEncoder()
        if args.frames:
            from analysis.policy_frames import policy_frames

            paths = glob_episode_files(args.frames)
            if not paths:
                raise ConfigError(f"--frames {args.frames}: no recorded episode matches")
            frames = policy_frames(paths, policy.cameras, encoder, every=args.every)
            result = {"frames": len(frames), "action_change": action_change(policy, frames, args.sigma)}
            for s, v in result["action_change"].items():
                print(f"sigma {s}: the mean action moves by {v:.4f} (RMS, normalised units) on {len(frames)} frames")
        else:
            from stages.post_train_loop.training import placements
            from worldenv_core.rl.real_rollouts import collect_member_outcomes

            numbers = [k for f in files for k in json.loads(f.read_text())["contexts"]]
            start = placements(contract)
            starts = [start(k) for k in numbers]
            ms = members(args.sigma, args.pairs, args.seed)
            out = collect_member_outcomes(args.policy, contract, [s for s, _ in starts], [i for _, i in starts], ms,
                                          encoder, contract.max_steps, workers=args.workers, progress=True,
                                          journal=args.journal)
            result = {"ledger": str(args.ledger), "iterations": args.iterations, "contexts": numbers,
                      "tasks": [s.task_id for s, _ in starts], "members": ms, "real_episodes": out["episodes"],
                      "successes": by_member(out["success"], args.sigma, args.pairs)}
            for name, per_start in result["successes"].items():
                n = 1 if name == "policy" else 2 * args.pairs
                print(f"{name}: {sum(per_start)} of {n * len(per_start)} on {len(per_start)} starts ({per_start})")
            print(f"{out['episodes']} real episodes")
        result.update(policy=args.policy, sigmas=args.sigma)
        if args.json:
            write_text_atomic(args.json, json.dumps(result, indent=1, default=str))
        return result


if __name__ == "__main__":
    main()
