"""A latent pack: a world model's open-loop training set as one safetensors file, so that
`train_worldsim init_from=<model> latents_from=<pack>` (phase 3) runs on a machine that has
neither the episodes nor the simulator (a rented GPU).

Phase 3 keeps the autoencoder of the model it goes on from, so a training frame only ever enters
it as that autoencoder's latent. The pack holds those latents (fp16, 2 KB a frame: 13 MB for
libero_goal's 40 training demos, whose MCAP files are ~100 MB), each episode's proprio states,
actions, joint angles and task id, its key, the task contract, each task's arm (for a model whose maps
draw it), and the sha256 of the autoencoder that encoded it
(a pack made by another model is refused). The model's held-out episodes are left out, as
`init_from=` leaves them out. `train_worldsim init_from=<model> latents_to=<pack>` writes one."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open

from worldenv_core.models.checkpoint import WEIGHTS, CheckpointError
from worldenv_core.models.worldsim_data import LatentChunks
from worldenv_core.packs import open_pack, write_pack

FORMAT = "worldenv-latent-pack-1"


@dataclass
class PackedMeta:
    task_id: int
    source: str | None = None  # "expert" / "policy" / "import"; None in a pack written before sources were kept


@dataclass
class PackedEpisode:
    """What `LatentChunks` reads of an episode, without its frames."""
    proprio: np.ndarray  # (T + 1, proprio_dim)
    actions: np.ndarray  # (T, action_dim)
    meta: PackedMeta
    joint_pos: np.ndarray | None = None  # (T + 1, 7); None in a pack written before joints were kept

    @property
    def length(self) -> int:
        return len(self.actions)


@dataclass
class LatentPack:
    latents: list[torch.Tensor]  # float32 (T + 1, C, h, w) per episode
    episodes: list[PackedEpisode]
    keys: list[str]
    task: dict                   # the task contract's meta it was made under
    encoder_sha256: str
    arms: dict | None = None     # task id -> `SerialArm.to_dict()` of its scene (None: an older pack)

    def every(self, n: int) -> "LatentPack":
        """Every n-th episode only (a data curve from one pack)."""
        return LatentPack(self.latents[::n], self.episodes[::n], self.keys[::n], self.task, self.encoder_sha256,
                          self.arms)

    def chunks(self, model, chunks_ahead: int) -> LatentChunks:
        return LatentChunks(self.latents, self.episodes, model.memory_offsets, model.chunk, chunks_ahead)


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


def write_latent_pack(path: str | Path, latents: list[torch.Tensor], episodes, keys: list[str],
                      model_dir: str | Path, camera: str, task: dict, arms: dict | None = None) -> Path:
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
        tensors[f"joint_pos.{i}"] = torch.from_numpy(np.ascontiguousarray(ep.joint_pos, dtype=np.float64))
    meta = {"format": FORMAT, "keys": json.dumps(keys), "task_ids": json.dumps([int(ep.meta.task_id) for ep in episodes]),
            "sources": json.dumps([ep.meta.source for ep in episodes]),
            "camera": camera, "encoder_sha256": encoder_sha256(model_dir), "task": json.dumps(task),
            **({"arms": json.dumps({str(t): a for t, a in arms.items()})} if arms else {})}
    return write_pack(path, tensors, meta)


def read_latent_pack(path: str | Path, model_dir: str | Path) -> LatentPack:
    """The pack, which must come from `model_dir`'s autoencoder."""
    with open_pack(path, FORMAT, "a latent pack",
                   f"python -m stages.train_worldsim +task=<task> init_from=<model> latents_to={path}",
                   wrong=CheckpointError) as (f, meta):
        if meta["encoder_sha256"] != encoder_sha256(model_dir):
            raise CheckpointError(f"{path} was encoded by another autoencoder than {model_dir}'s: its latents would not be "
                                  "this model's; pack again from this model")
        task_ids = json.loads(meta["task_ids"])
        sources = json.loads(meta["sources"]) if "sources" in meta else [None] * len(task_ids)
        latents = [f.get_tensor(f"latents.{i}").float() for i in range(len(task_ids))]
        names = set(f.keys())
        episodes = [PackedEpisode(f.get_tensor(f"proprio.{i}").numpy(), f.get_tensor(f"actions.{i}").numpy(),
                                  PackedMeta(t, sources[i]), f.get_tensor(f"joint_pos.{i}").numpy() if f"joint_pos.{i}" in names else None)
                    for i, t in enumerate(task_ids)]
    arms = {int(t): a for t, a in json.loads(meta["arms"]).items()} if "arms" in meta else None
    return LatentPack(latents, episodes, json.loads(meta["keys"]), json.loads(meta.get("task", "{}")),
                      meta["encoder_sha256"], arms)
