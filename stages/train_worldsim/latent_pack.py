"""A latent pack: a world model's open-loop training set as one safetensors file, for phase 3 of
`train_worldsim` on a machine that has neither the episodes nor the simulator (a rented GPU;
`from_pack` trains there).

Phase 3 keeps the autoencoder of the model it goes on from, so a training frame only ever enters
it as that autoencoder's latent. The pack holds those latents (fp16, 2 KB a frame: 13 MB for
libero_goal's 40 training demos, whose MCAP files are ~100 MB), each episode's proprio states,
actions and task id, its key, and the sha256 of the autoencoder that encoded it (`from_pack` refuses a
pack made by another model). The model's held-out episodes are left out, as `init_from=` does.

    python -m stages.train_worldsim.latent_pack checkpoints/libero_goal/worldsim_open_loop \\
        'data/libero_goal/expert-73fe2c9a/task*/*.mcap' --out pack.safetensors
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from worldenv_core.models.checkpoint import WEIGHTS, CheckpointError, read_config
from worldenv_core.models.worldsim_data import LatentChunks, encode_episode_frames

FORMAT = "worldenv-latent-pack-1"


@dataclass
class PackedMeta:
    task_id: int


@dataclass
class PackedEpisode:
    """What `LatentChunks` reads of an episode, without its frames."""
    proprio: np.ndarray  # (T + 1, proprio_dim)
    actions: np.ndarray  # (T, action_dim)
    meta: PackedMeta

    @property
    def length(self) -> int:
        return len(self.actions)


def encoder_sha256(model_dir: str | Path) -> str:
    """What fixes a model's latents: its autoencoder's weights and latent scale (phase 3 changes
    neither, so a pack serves every model trained on from the one that made it)."""
    with safe_open(str(Path(model_dir) / WEIGHTS), framework="pt") as f:
        keys = sorted(k for k in f.keys() if k.startswith("autoencoder.") or k == "latent_scale")
        h = hashlib.sha256()
        for k in keys:
            h.update(k.encode())
            h.update(f.get_tensor(k).numpy().tobytes())
    return h.hexdigest()


def write_pack(path: str | Path, latents: list[torch.Tensor], episodes, keys: list[str], model_dir: str | Path,
               camera: str) -> Path:
    """Latents (T + 1, C, h, w) per episode, beside the episodes they came from, written to a
    temporary name and renamed when complete."""
    if not (len(latents) == len(episodes) == len(keys)) or not latents:
        raise ValueError(f"a pack needs one latent sequence per episode: {len(latents)} latents, {len(episodes)} "
                         f"episodes, {len(keys)} keys")
    tensors = {}
    for i, (z, ep) in enumerate(zip(latents, episodes)):
        if len(z) != len(ep.proprio):
            raise ValueError(f"episode {keys[i]}: {len(z)} latents for {len(ep.proprio)} frames")
        tensors[f"latents.{i}"] = z.to(torch.float16).contiguous()
        tensors[f"proprio.{i}"] = torch.from_numpy(np.ascontiguousarray(ep.proprio, dtype=np.float32))
        tensors[f"actions.{i}"] = torch.from_numpy(np.ascontiguousarray(ep.actions, dtype=np.float32))
    meta = {"format": FORMAT, "keys": json.dumps(keys), "task_ids": json.dumps([int(ep.meta.task_id) for ep in episodes]),
            "camera": camera, "encoder_sha256": encoder_sha256(model_dir)}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    os.replace(tmp, path)
    return path


def read_pack(path: str | Path, model_dir: str | Path) -> tuple[list[torch.Tensor], list[PackedEpisode], dict]:
    """-> (float32 latents per episode, episodes, metadata); the pack must come from `model_dir`'s weights."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no latent pack at {path}: write one with `python -m stages.train_worldsim.latent_pack`")
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        if meta.get("format") != FORMAT:
            raise CheckpointError(f"{path} is not a latent pack (format {meta.get('format')!r}, expected {FORMAT!r})")
        if meta["encoder_sha256"] != encoder_sha256(model_dir):
            raise CheckpointError(f"{path} was encoded by another autoencoder than {model_dir}'s: its latents would not be "
                                  "this model's; pack again from this model")
        task_ids = json.loads(meta["task_ids"])
        latents = [f.get_tensor(f"latents.{i}").float() for i in range(len(task_ids))]
        episodes = [PackedEpisode(f.get_tensor(f"proprio.{i}").numpy(), f.get_tensor(f"actions.{i}").numpy(),
                                  PackedMeta(t)) for i, t in enumerate(task_ids)]
    return latents, episodes, meta


def pack_chunks(latents, episodes, model, chunks_ahead: int) -> LatentChunks:
    return LatentChunks(latents, episodes, model.memory_offsets, model.chunk, chunks_ahead)


def main(argv: list[str] | None = None) -> Path:
    from worldenv_core.data.selection import episode_key, expand_episode_paths, load_split
    from worldenv_core.models.checkpoint import load_checkpoint

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the world model checkpoint folder that phase 3 goes on from")
    p.add_argument("episodes", nargs="+", help="episode files or glob patterns (its held-out ones are left out)")
    p.add_argument("--out", required=True, help="the pack file to write")
    args = p.parse_args(argv)
    paths = expand_episode_paths(args.episodes)
    model, meta = load_checkpoint(args.model, "worldsim")
    train, _, episodes, _ = load_split(paths, 0, meta["camera"], meta["held_out"])
    latents = [encode_episode_frames(model, ep.images[meta["camera"]]) for ep in episodes]
    out = write_pack(args.out, latents, episodes, [episode_key(q) for q in train], args.model, meta["camera"])
    frames = sum(len(z) for z in latents)
    print(f"{out}: {len(episodes)} episodes, {frames} frames, {out.stat().st_size / 2**20:.1f} MiB "
          f"({len(meta['held_out'])} held-out keys of the model left out)")
    return out


if __name__ == "__main__":
    main()
