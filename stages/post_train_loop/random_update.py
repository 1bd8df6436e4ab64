"""The random-update control: a policy's weights moved as far as a post-trained policy moved them,
tensor by tensor, in a random direction.

A post-trained policy that beats its SFT start may have gained from what the rewards said or merely
from being moved a little away from the SFT weights. This control keeps the size of the update
(each tensor's change has the post-trained policy's L2 norm) and throws away its direction (seeded
Gaussian), so a real evaluation of it, paired with both, says which: a gain it shares is not RL's.
Tensors the update left unchanged (normalisation statistics) stay unchanged. At the same norm a
random direction changes the actions far less than a gradient step does, so `--scale` sets the size
and `--frames` measures both changes of the mean action on recorded frames, to match them.

`--mirror` writes the opposite control: the start moved by minus the update (the same size, the reverse
direction). Near the start a move's first-order effect flips sign with it and its second-order effect
does not, so if the post-trained policy gains from what the rewards said its mirror loses, and if it
gains only from leaving a start that sits low in its neighbourhood its mirror gains as well.

    python -m stages.post_train_loop.random_update --policy checkpoints/libero_spatial/sft \\
        --like <post_train_loop work>/policy --out outputs/libero_spatial-small/random_update/seed0 --seed 0 --scale 16 \\
        --frames "data/libero_spatial/expert-*/task*/expert_0000.mcap"
    python -m stages.post_train_loop.random_update --policy checkpoints/libero_spatial/sft \\
        --like <post_train_loop work>/policy --out outputs/libero_spatial-small/random_update/mirror --mirror
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from stages.evaluate.keep import portable
from worldenv_core.cli import user_errors
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.data.selection import expand_episode_paths
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import WEIGHTS, load_checkpoint, load_weights, read_config, save_state


def _check_pair(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor], scale: float) -> None:
    if not scale > 0:
        raise ConfigError(f"scale must be > 0, got {scale}")
    if base.keys() != like.keys():
        raise ConfigError(f"the two policies have different tensors (only in the first: "
                          f"{sorted(base.keys() - like.keys())[:3]}, only in the second: {sorted(like.keys() - base.keys())[:3]})")
    for name, a in base.items():
        if a.shape != like[name].shape:
            raise ConfigError(f"tensor {name} has shape {tuple(a.shape)} in the first policy, "
                              f"{tuple(like[name].shape)} in the second")


def random_update(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor], seed: int,
                  scale: float = 1.0) -> tuple[dict[str, torch.Tensor], int]:
    """`base` + a random direction per tensor with `scale` x the norm of `like - base`. -> (state, tensors moved)"""
    _check_pair(base, like, scale)
    generator = torch.Generator().manual_seed(seed)
    out, moved = {}, 0
    for name in sorted(base):  # sorted: the draw for a tensor does not depend on the file's order
        a, b = base[name], like[name]
        norm = float((b.double() - a.double()).norm()) if a.is_floating_point() else 0.0
        if norm == 0.0:
            out[name] = a.clone()
            continue
        direction = torch.randn(a.shape, generator=generator, dtype=torch.float64)
        out[name] = (a.double() + direction * (scale * norm / float(direction.norm()))).to(a.dtype)
        moved += 1
    return out, moved


def mirror_update(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor],
                  scale: float = 1.0) -> tuple[dict[str, torch.Tensor], int]:
    """`base` - `scale` x (`like` - `base`): the update reflected through the start. -> (state, tensors moved)"""
    _check_pair(base, like, scale)
    out, moved = {}, 0
    for name, a in base.items():
        b = like[name]
        if not a.is_floating_point() or torch.equal(a, b):
            out[name] = a.clone()
            continue
        out[name] = (a.double() - scale * (b.double() - a.double())).to(a.dtype)
        moved += 1
    return out, moved


@torch.no_grad()
def action_changes(base: torch.nn.Module, moved: list[torch.nn.Module], files: list, every: int = 8) -> list[float]:
    """RMS change of the mean action chunk (the policy's normalised units) from `base` to each of `moved`
    on every `every`-th frame of the recorded episodes in `files` (each episode read and encoded once)."""
    from worldenv_core.models.text import InstructionEncoder

    encoder, diffs = InstructionEncoder(), [[] for _ in moved]
    for file in files:
        episode = read_episode(file, cameras=base.cameras)
        frames = np.arange(0, len(episode.proprio), every)
        images = {c: episode.video(c)[frames] for c in base.cameras}
        inputs = (images, torch.as_tensor(episode.proprio[frames]), encoder([episode.meta.instruction] * len(frames)))
        start = base(*inputs)[0]
        for out, model in zip(diffs, moved):
            out.append(model(*inputs)[0] - start)
    return [float(torch.cat(d).pow(2).mean().sqrt()) for d in diffs]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", required=True, help="the policy to move (the SFT checkpoint folder)")
    ap.add_argument("--like", required=True, help="a policy post-trained from it: the size of the move, per tensor")
    ap.add_argument("--out", required=True, help="the checkpoint folder to write")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0,
                    help="x the post-trained change's norm per tensor; a random direction moves the actions far less "
                         "than a gradient's does at the same norm, so match their change in actions with this")
    ap.add_argument("--mirror", action="store_true",
                    help="move by minus the post-trained update (x --scale) instead of in a random direction")
    ap.add_argument("--frames", nargs="*", default=[],
                    help="recorded episodes (files, folders or globs) to measure both changes of the mean action on")
    args = ap.parse_args(argv)
    with user_errors():
        configs = [read_config(p) for p in (args.policy, args.like)]
        for path, cfg in zip((args.policy, args.like), configs):
            if cfg["meta"].get("kind") != "policy":
                raise ConfigError(f"{path} holds a {cfg['meta'].get('kind')!r} checkpoint, not a policy")
        if configs[0]["model"] != configs[1]["model"]:
            raise ConfigError(f"{args.policy} and {args.like} are built from different model configs: "
                              "--like must be post-trained from --policy")
        files = expand_episode_paths(args.frames) if args.frames else []
        base, like = (load_weights(Path(p) / WEIGHTS) for p in (args.policy, args.like))
        state, moved = (mirror_update(base, like, args.scale) if args.mirror
                        else random_update(base, like, args.seed, args.scale))
        direction = "the reverse of its update" if args.mirror else f"a random direction (seed {args.seed})"
        meta = {**configs[0]["meta"], "random_update": {"from": portable(args.policy), "like": portable(args.like),
                                                        "direction": "mirror" if args.mirror else "random",
                                                        "seed": None if args.mirror else args.seed,
                                                        "scale": args.scale, "tensors_moved": moved}}
        save_state(args.out, state, configs[0]["model"], meta)
        print(f"{args.out}: {moved} tensors moved {args.scale:g} x as far as in {args.like}, in {direction}")
        if files:
            base, like, out = (load_checkpoint(p, "policy")[0] for p in (args.policy, args.like, args.out))
            post_trained, this = action_changes(base, [like, out], files)
            print(f"RMS change of the mean action on every 8th frame of {len(files)} episodes (normalised units): "
                  f"{post_trained:.4f} post-trained, {this:.4f} this move")


if __name__ == "__main__":
    main()
