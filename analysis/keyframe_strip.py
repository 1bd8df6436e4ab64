"""What a world model imagines from a recorded keyframe, as a picture: per keyframe, the recorded episode's own
frames from there (what really happened) above the policy's imagined rollout in each world model given, a frame
every `--every` steps, each imagined row labelled with where the reward model's verdict fired (the imagined
rollout stops there). `--sampler-noise 1 --sampling-steps 4` shows the sampled generator instead of the mean. No physics: the recorded row is the episode as it was collected (its own, noisier actions).

    python -m analysis.keyframe_strip +task=libero_spatial --policy checkpoints/libero_spatial/sft \\
        --episodes "data/libero_spatial/policy-*/task03/policy_0051.mcap" --depth 0.35 0.7 \\
        --worldsim checkpoints/libero_spatial/worldsim_demo_flow <another> --out docs/img/strip.jpg
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError


def imagined_frames(policy, env, context, encoder) -> tuple[list[np.ndarray], int | None]:
    """The policy's mean actions from one context in `env` -> (frames HxWx3 uint8 at each chunk boundary, the
    step where the verdict fired or None)."""
    state = env.reset([context])
    lang = encoder([context.instruction])
    camera = policy.cameras[0]
    frames = [state.frames[0]]
    with torch.no_grad():
        while not state.done.all():
            mu = policy({camera: state.frames}, state.proprio, lang)[0]
            state = env.step(policy.unnormalize_actions(mu))
            frames.append(state.frames[0])
    fired = int(state.t[0]) if bool(state.by_reflector[0]) else None
    return [as_image(f) for f in frames], fired


def as_image(frame: torch.Tensor) -> np.ndarray:
    """A (3, H, W) frame, uint8 or float in [0, 1] -> HxWx3 uint8."""
    x = frame.detach().cpu().permute(1, 2, 0).numpy()
    return x if x.dtype == np.uint8 else (x * 255).clip(0, 255).round().astype(np.uint8)


def pick(frames: list[np.ndarray], steps: list[int], per_frame: int) -> list[np.ndarray]:
    """The frames at `steps` (env steps) from frames `per_frame` steps apart; past the end, the last one darkened
    (the rollout had stopped)."""
    out = []
    for s in steps:
        i = s // per_frame
        out.append(frames[i] if i < len(frames) else (frames[-1] * 0.4).astype(np.uint8))
    return out


def draw(rows: list[tuple[str, list[np.ndarray]]], steps: list[int], path: str | Path, title: str = "") -> Path:
    """One labelled row of frames per (label, frames)."""
    from worldenv_core.viz import figure, save_figure

    n, m = len(rows), len(steps)
    fig, axes = figure(n, m, figsize=(1.6 * m + 1.2, 1.7 * n + 0.4), squeeze=False)
    for r, (label, frames) in enumerate(rows):
        for c, img in enumerate(frames):
            ax = axes[r][c]
            ax.imshow(img)
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(f"+{steps[c]} steps", fontsize=7)
        axes[r][0].set_ylabel(label, fontsize=6, rotation=0, ha="right", va="center")
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True, help="the policy acting in imagination (checkpoint folder)")
    ap.add_argument("--episodes", nargs="+", required=True, help="recorded episodes (globs), a keyframe each")
    ap.add_argument("--depth", type=float, nargs=2, default=[0.35, 0.7], help="where the keyframe lies")
    ap.add_argument("--worldsim", nargs="+", required=True, help="world-simulator checkpoints, a row each")
    ap.add_argument("--reflector", help="reflector checkpoint (default: checkpoints/<suite>/reflector)")
    ap.add_argument("--horizon", type=int, default=64, help="imagined steps")
    ap.add_argument("--every", type=int, default=16, help="steps between the frames shown")
    ap.add_argument("--sampling-steps", type=int, help="the flow sampler's steps (default: each model's own)")
    ap.add_argument("--sampler-noise", type=float, help="the flow sampler's temperature in [0, 1] (default: its own)")
    ap.add_argument("--robot-layer", action="store_true",
                    help="also each model with the robot drawn by the real renderer (`imagination.robot_layer`)")
    ap.add_argument("--out", type=Path, required=True, help="the picture (png / jpg)")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=...)")
    args = ap.parse_args(argv)
    with user_errors():
        from analysis.imagined_ledger import require_checkpoints
        from stages.post_train_loop.training import contexts_from_episodes
        from worldenv_core.data.mcap_io.read import glob_episode_files, read_episode
        from worldenv_core.imagination.env import build_imagined_env, check_depth
        from worldenv_core.models.checkpoint import load_checkpoint
        from worldenv_core.models.text import InstructionEncoder
        from worldenv_core.rl.termination import reflector_eta
        from worldenv_core.stage import compose_config, task_contract

        try:
            check_depth(args.depth)
        except ValueError as e:
            raise ConfigError(f"--depth: {e}") from None
        if args.every <= 0 or args.horizon <= 0:
            raise ConfigError(f"--every and --horizon must be positive, got {args.every} and {args.horizon}")
        paths = glob_episode_files(args.episodes)
        if not paths:
            raise ConfigError(f"--episodes {args.episodes}: no recorded episode matches")
        contract = task_contract(compose_config("post_train_loop", ["scale=small", *args.overrides]))
        reflector = args.reflector or f"checkpoints/{contract.suite}/reflector"
        require_checkpoints([("--reflector", reflector), ("--policy", args.policy),
                             *(("--worldsim", w) for w in args.worldsim)])
        encoder = InstructionEncoder()
        policy, _ = load_checkpoint(args.policy, "policy", contract, device="cpu")
        policy.eval()
        variants = [(w, False) for w in args.worldsim] + [(w, True) for w in args.worldsim if args.robot_layer]
        envs = [build_imagined_env(w, reflector, reflector_eta(reflector, None), encoder, args.horizon,
                                   args.sampling_steps, "cpu", contract, args.sampler_noise, robot_layer=robot)
                for w, robot in variants]
        camera = envs[0][1]
        steps = list(range(0, args.horizon + 1, args.every))
        rows, found = [], []
        for path in paths:
            contexts, starts = contexts_from_episodes([path], camera, 1, tuple(args.depth), contract.chunk)
            k = int(starts[0].key.rsplit("@", 1)[1])
            recorded = read_episode(path, cameras=[camera]).images[camera]
            rows.append((f"{path.parent.name}/{path.stem}@{k}\nrecorded", [recorded[min(k + s, len(recorded) - 1)]
                                                                           for s in steps]))
            for (w, robot), (env, _) in zip(variants, envs):
                frames, fired = imagined_frames(policy, env, contexts[0], encoder)
                verdict = f"success at +{fired}" if fired is not None else "no success"
                name = "/".join(Path(w).parts[-2:]) + (" + robot layer" if robot else "")
                rows.append((f"{name}\n{verdict}", pick(frames, steps, contract.chunk)))
                found.append({"episode": str(path), "frame": k, "worldsim": w, "robot_layer": robot,
                              "verdict_step": fired})
                print(f"{path}@{k} in {name}: {verdict}", flush=True)
        draw(rows, steps, args.out)
        print(f"wrote {args.out}")
        return found


if __name__ == "__main__":
    main()
