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

Several `--like` policies (post-trained from the same start with other seeds) stand for their mean update:
what the seeds' updates share survives the mean, what each drew by chance partly cancels. `--along` moves
the start along that update itself (x `--scale`), `--mirror` against it, and the default in a random
direction as large per tensor.

    python -m analysis.random_update --policy checkpoints/libero_spatial/sft \\
        --like <post_train_loop work>/policy --out outputs/libero_spatial-small/random_update/seed0 --seed 0 --scale 16 \\
        --frames "data/libero_spatial/expert-*/task*/expert_0000.mcap"
    python -m analysis.random_update --policy checkpoints/libero_spatial/sft \\
        --like <post_train_loop work>/policy --out outputs/libero_spatial-small/random_update/mirror --mirror
    python -m analysis.random_update --policy checkpoints/libero_spatial/sft \\
        --like checkpoints/libero_spatial/real_reference_seed1 checkpoints/libero_spatial/real_reference_seed2 \\
        --out outputs/libero_spatial-small/random_update/mean_real_seeds12 --along
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from analysis.keep import portable
from analysis.policy_frames import mean_actions, policy_frames
from worldenv_core.cli import user_errors
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


def mean_update(base: dict[str, torch.Tensor], likes: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The state `base` + the mean of (`like` - `base`) over `likes`: several seeds' updates as one."""
    if not likes:
        raise ConfigError("mean_update needs at least one post-trained state")
    for like in likes:
        _check_pair(base, like, 1.0)
    if len(likes) == 1:
        return likes[0]
    out = {}
    for name, a in base.items():
        if not a.is_floating_point():
            out[name] = a.clone()
            continue
        mean = sum(like[name].double() - a.double() for like in likes) / len(likes)
        out[name] = (a.double() + mean).to(a.dtype)
    return out


def scaled_update(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor],
                  factor: float) -> tuple[dict[str, torch.Tensor], int]:
    """`base` + `factor` x (`like` - `base`): along the update (factor > 0) or reflected through the start
    (factor < 0). Tensors the update left unchanged stay unchanged. -> (state, tensors moved)"""
    _check_pair(base, like, abs(factor))
    out, moved = {}, 0
    for name, a in base.items():
        b = like[name]
        if not a.is_floating_point() or torch.equal(a, b):
            out[name] = a.clone()
            continue
        out[name] = (a.double() + factor * (b.double() - a.double())).to(a.dtype)
        moved += 1
    return out, moved


def mirror_update(base: dict[str, torch.Tensor], like: dict[str, torch.Tensor],
                  scale: float = 1.0) -> tuple[dict[str, torch.Tensor], int]:
    """`base` - `scale` x (`like` - `base`): the update reflected through the start. -> (state, tensors moved)"""
    return scaled_update(base, like, -scale)


@torch.no_grad()
def action_deltas(base: torch.nn.Module, moved: list[torch.nn.Module], files: list, every: int = 8) -> list[torch.Tensor]:
    """Change of the mean action chunk (the policy's normalised units) from `base` to each of `moved`, flattened,
    on every `every`-th frame of the recorded episodes in `files` (each episode read and encoded once)."""
    from worldenv_core.models.text import InstructionEncoder

    frames = policy_frames(files, base.cameras, InstructionEncoder(), every)
    start = mean_actions(base, frames)
    return [(mean_actions(model, frames) - start).flatten() for model in moved]


def action_changes(base: torch.nn.Module, moved: list[torch.nn.Module], files: list, every: int = 8) -> list[float]:
    """RMS change of the mean action from `base` to each of `moved` (see `action_deltas`)."""
    return [float(d.pow(2).mean().sqrt()) for d in action_deltas(base, moved, files, every)]


def read_policies(policy: str, likes: list[str]) -> tuple[dict, dict[str, torch.Tensor], list[dict[str, torch.Tensor]]]:
    """The start's config and weights and the weights of policies post-trained from it, refusing a folder that
    holds no policy or a policy of another model. -> (the start's config, its state, their states)"""
    configs = [read_config(p) for p in (policy, *likes)]
    for path, cfg in zip((policy, *likes), configs):
        if cfg["meta"].get("kind") != "policy":
            raise ConfigError(f"{path} holds a {cfg['meta'].get('kind')!r} checkpoint, not a policy")
    for path, cfg in zip(likes, configs[1:]):
        if cfg["model"] != configs[0]["model"]:
            raise ConfigError(f"{policy} and {path} are built from different model configs: "
                              "--like must be post-trained from --policy")
    return configs[0], load_weights(Path(policy) / WEIGHTS), [load_weights(Path(p) / WEIGHTS) for p in likes]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", required=True, help="the policy to move (the SFT checkpoint folder)")
    ap.add_argument("--like", required=True, nargs="+",
                    help="a policy post-trained from it (the size of the move, per tensor); several: their mean update")
    ap.add_argument("--out", required=True, help="the checkpoint folder to write")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0,
                    help="x the post-trained change's norm per tensor; a random direction moves the actions far less "
                         "than a gradient's does at the same norm, so match their change in actions with this")
    direction = ap.add_mutually_exclusive_group()
    direction.add_argument("--mirror", action="store_true",
                           help="move by minus the post-trained update (x --scale) instead of in a random direction")
    direction.add_argument("--along", action="store_true",
                           help="move by the post-trained update itself (x --scale): with several --like, their mean")
    ap.add_argument("--frames", nargs="*", default=[],
                    help="recorded episodes (files, folders or globs) to measure both changes of the mean action on")
    args = ap.parse_args(argv)
    with user_errors():
        config, base, likes = read_policies(args.policy, args.like)
        files = expand_episode_paths(args.frames) if args.frames else []
        like = mean_update(base, likes)
        kind = "mirror" if args.mirror else "update" if args.along else "random"
        if kind == "random":
            state, moved = random_update(base, like, args.seed, args.scale)
        else:
            state, moved = scaled_update(base, like, -args.scale if kind == "mirror" else args.scale)
        update = "its update" if len(args.like) == 1 else f"the mean of their {len(args.like)} updates"
        direction = {"mirror": f"the reverse of {update}", "update": f"the direction of {update}",
                     "random": f"a random direction (seed {args.seed})"}[kind]
        likes = [portable(p) for p in args.like]
        meta = {**config["meta"], "random_update": {"from": portable(args.policy),
                                                        "like": likes[0] if len(likes) == 1 else likes,
                                                        "direction": kind, "seed": args.seed if kind == "random" else None,
                                                        "scale": args.scale, "tensors_moved": moved}}
        save_state(args.out, state, config["model"], meta)
        print(f"{args.out}: {moved} tensors moved {args.scale:g} x as far as in {' and '.join(args.like)}, in {direction}")
        if files:
            base, out, *likes = (load_checkpoint(p, "policy")[0] for p in (args.policy, args.out, *args.like))
            *post_trained, this = action_changes(base, [*likes, out], files)
            print(f"RMS change of the mean action on every 8th frame of {len(files)} episodes (normalised units): "
                  f"{', '.join(f'{c:.4f}' for c in post_trained)} post-trained, {this:.4f} this move")

if __name__ == "__main__":
    main()
