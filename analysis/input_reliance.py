"""Does a policy read its inputs? The change of its mean action chunk when one input is taken from another frame.

A policy that fits its demos from the proprio alone (or whose image features died in training) predicts nearly
the same chunk whatever the camera shows, and fails as soon as a scene differs from the demos'. On recorded
frames, each input in turn (the image, the proprio, the instruction) is replaced by another frame's (a fixed
derangement: no frame keeps its own) while the others stay, and the chunk's mean absolute change is reported
beside the chunk's spread over the frames (what a change can be compared with). A vision backbone's output
magnitude is reported where the policy has one (LeRobot's ACT: `act.model.backbone`), since features that grew
without bound stop carrying the image. No simulator: seconds on a CPU.

    python -m analysis.input_reliance --policy checkpoints/libero_spatial/sft <an ACT policy folder> \\
        --frames "data/libero_spatial/expert-*/task*/expert_0000.mcap"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from analysis.policy_frames import PolicyFrames, mean_actions, policy_frames
from worldenv_core.cli import user_errors
from worldenv_core.data.selection import expand_episode_paths
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic

INPUTS = ("image", "proprio", "instruction")


def derangement(n: int, seed: int = 0) -> torch.Tensor:
    """A permutation of 0..n-1 that moves every index (n >= 2): a random one, each fixed point swapped away."""
    if n < 2:
        raise ValueError("swapping an input between frames needs at least two frames")
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    for i in range(n):
        if perm[i] == i:  # swap with the next position: both then move (perm is a permutation)
            j = (i + 1) % n
            perm[i], perm[j] = perm[j].clone(), perm[i].clone()
    return perm


def swapped(frames: PolicyFrames, which: str, perm: torch.Tensor) -> PolicyFrames:
    """`frames` with input `which` taken from frame perm[i] in row i."""
    return PolicyFrames({c: v[perm] for c, v in frames.images.items()} if which == "image" else frames.images,
                        frames.proprio[perm] if which == "proprio" else frames.proprio,
                        frames.instruction[perm] if which == "instruction" else frames.instruction, frames.task_ids)


@torch.no_grad()
def backbone_magnitude(policy: torch.nn.Module, frames: PolicyFrames, batch: int = 64) -> dict | None:
    """LeRobot ACT's ResNet output on the frames: its mean |value| and the share of exact zeros (dead units);
    None for a policy without that backbone."""
    act = getattr(policy, "act", None)
    if act is None or not hasattr(policy, "inputs"):
        return None
    total, zeros, count = 0.0, 0, 0
    for i in range(0, len(frames), batch):
        imgs = policy.inputs(*frames.rows(slice(i, i + batch)))["observation.images"]
        for x in imgs:
            f = act.model.backbone(x)["feature_map"]
            total, zeros, count = total + float(f.abs().sum()), zeros + int((f == 0).sum()), count + f.numel()
    return {"backbone_mean_abs": total / count, "backbone_zero_share": zeros / count}


@torch.no_grad()
def input_reliance(policy: torch.nn.Module, frames: PolicyFrames, seed: int = 0) -> dict:
    """-> the chunk's spread over the frames (mean over its entries of the std over frames, in the policy's
    normalised action space), and for each input the mean |change| of the chunk when it is swapped, alone and as
    a share of the spread."""
    policy.eval()
    base = mean_actions(policy, frames)
    perm = derangement(len(frames), seed)
    spread = float(base.std(0).mean())
    out = {"frames": len(frames), "chunk_spread": spread}
    for which in INPUTS:
        change = float((mean_actions(policy, swapped(frames, which, perm)) - base).abs().mean())
        out[f"{which}_change"] = change
        out[f"{which}_share"] = change / spread if spread > 0 else float("nan")
    return {**out, **(backbone_magnitude(policy, frames) or {})}


def table(rows: dict[str, dict]) -> str:
    head = "| policy | frames | chunk spread | " + " | ".join(f"{w} swapped (share)" for w in INPUTS) + " |"
    lines = [head, "|" + "---|" * (len(INPUTS) + 3)]
    for name, r in rows.items():
        cells = " | ".join(f"{r[f'{w}_change']:.3g} ({r[f'{w}_share']:.2f})" for w in INPUTS)
        lines.append(f"| {name} | {r['frames']} | {r['chunk_spread']:.3g} | {cells} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", required=True, nargs="+", help="policy checkpoint folders")
    ap.add_argument("--frames", required=True, nargs="+", help="recorded episodes (files, folders or globs)")
    ap.add_argument("--every", type=int, default=8, help="every n-th frame (the policy reads one per chunk)")
    ap.add_argument("--seed", type=int, default=0, help="the derangement's seed")
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args(argv)
    with user_errors():
        from worldenv_core.models.checkpoint import load_checkpoint
        from worldenv_core.models.text import InstructionEncoder

        try:
            files = expand_episode_paths(args.frames)
        except FileNotFoundError as e:
            raise ConfigError(f"--frames: {e}") from None
        policies = {p: load_checkpoint(p, "policy")[0] for p in args.policy}
        encoder, rows, read = InstructionEncoder(), {}, {}
        for path, policy in policies.items():
            cams = tuple(policy.cameras)  # policies that look at the same cameras share one read of the episodes
            if cams not in read:
                read[cams] = policy_frames(files, list(cams), encoder, every=args.every)
            rows[path] = input_reliance(policy, read[cams], args.seed)
        print(table(rows))
        if args.json:
            write_text_atomic(Path(args.json), json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
