"""How far post-training runs agree: the cosine between their updates, in the weights and in the actions.

Runs of the same post-training from one start with different seeds each move the weights by an update that is
partly what the reward says (shared by every seed) and partly what its seed drew (its own). With a shared part s
and independent parts n_i as large as each other, two updates' cosine is |s|^2 / (|s|^2 + |n|^2): near 1 the
seeds agree on where to go, near 0 each update is mostly its own draw, and the mean of K seeds' updates keeps s
while its drawn part shrinks by sqrt(K) (`random_update --along` with several `--like`). Weight cosines count
every parameter alike; action cosines (the change of the mean action on recorded frames) count what the policy
does. No simulator, no real episode: seconds on a CPU.

    python -m analysis.update_similarity --policy checkpoints/libero_spatial/sft \\
        --like checkpoints/libero_spatial/real_reference_seed1 checkpoints/libero_spatial/real_reference_seed2 \\
        checkpoints/libero_spatial/post_trained --frames "data/libero_spatial/expert-*/task*/expert_0000.mcap"
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from analysis.random_update import action_deltas, read_policies
from worldenv_core.cli import user_errors
from worldenv_core.data.selection import expand_episode_paths
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import load_checkpoint


def weight_update(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor]) -> torch.Tensor:
    """`like` - `base` over every floating-point tensor, flattened in name order (float64)."""
    return torch.cat([(like[k].double() - base[k].double()).flatten() for k in sorted(base) if base[k].is_floating_point()])


def cosines(vectors: list[torch.Tensor]) -> np.ndarray:
    """Pairwise cosine similarities; a zero vector has cosine 0 with everything (it points nowhere)."""
    stacked = torch.stack([v.double() for v in vectors])
    norms = stacked.norm(dim=1, keepdim=True)
    unit = torch.where(norms > 0, stacked / norms.clamp_min(1e-300), torch.zeros_like(stacked))
    return (unit @ unit.T).numpy()


def table(names: list[str], sizes: list[str], matrix: np.ndarray, what: str) -> str:
    head = f"| {what} | size | " + " | ".join(f"({i + 1})" for i in range(len(names))) + " |"
    rows = [f"| ({i + 1}) {n} | {size} | " + " | ".join(f"{c:+.3f}" for c in matrix[i]) + " |"
            for i, (n, size) in enumerate(zip(names, sizes))]
    return "\n".join([head, "|" + "---|" * (len(names) + 2), *rows])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", required=True, help="the start the runs post-trained from (the SFT checkpoint folder)")
    ap.add_argument("--like", required=True, nargs="+", help="policies post-trained from it (two or more)")
    ap.add_argument("--frames", nargs="*", default=[],
                    help="recorded episodes (files, folders or globs) to compare the changes of the mean action on")
    args = ap.parse_args(argv)
    with user_errors():
        if len(args.like) < 2:
            raise ConfigError("--like needs two or more post-trained policies to compare")
        files = expand_episode_paths(args.frames) if args.frames else []
        _, base, likes = read_policies(args.policy, args.like)
        updates = [weight_update(base, like) for like in likes]
        print(table(args.like, [f"{float(u.norm()):.4f}" for u in updates], cosines(updates),
                    "weights: cosine of the updates"))
        if files:
            start, *moved = (load_checkpoint(p, "policy")[0] for p in (args.policy, *args.like))
            deltas = action_deltas(start, moved, files)
            print(f"\nactions: every 8th frame of {len(files)} episodes; size = RMS change of the mean action")
            print(table(args.like, [f"{float(d.pow(2).mean().sqrt()):.4f}" for d in deltas], cosines(deltas),
                        "actions: cosine of the changes"))


if __name__ == "__main__":
    main()
