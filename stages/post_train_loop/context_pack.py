"""A context pack: LOOP's contexts as one safetensors file, for `post_train_loop.from_pack` on a
machine that has neither the episodes, the simulator nor the instruction encoder's weights (a
rented GPU). Imagined LOOP needs of an episode only the frame, proprio and instruction it starts
from, so the pack holds those (the frames as uint8, 49 KB each at 128 px), each instruction's
embedding by the encoder the policy was trained with, and where each context came from.

    python -m stages.post_train_loop.context_pack 'data/libero_goal/expert-73fe2c9a/task0[012]/*.mcap' \\
        --out contexts.safetensors [--mid-frames 2] [--camera agentview]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from worldenv_core.imagination.env import Context

FORMAT = "worldenv-context-pack-1"


class PackedInstructions:
    """The instruction encoder's interface (strings -> (B, D) embeddings) over the embeddings a
    pack carries; an instruction it does not carry is an error naming it."""

    def __init__(self, table: dict[str, torch.Tensor]):
        self.table = table

    def __call__(self, instructions: list[str]) -> torch.Tensor:
        missing = sorted({s for s in instructions if s not in self.table})
        if missing:
            raise KeyError(f"the context pack carries no embedding of {missing}")
        return torch.stack([self.table[s] for s in instructions])


def write_context_pack(path: str | Path, contexts: list[Context], keys: list[str], encoder, camera: str) -> Path:
    """The contexts, one embedding per distinct instruction, written to a temporary name and renamed
    when complete."""
    if not contexts or len(contexts) != len(keys):
        raise ValueError(f"a pack needs one key per context: {len(contexts)} contexts, {len(keys)} keys")
    instructions = sorted({c.instruction for c in contexts})
    tensors = {"frames": torch.stack([c.frame for c in contexts]).contiguous(),
               "proprio": torch.stack([torch.as_tensor(c.proprio, dtype=torch.float64) for c in contexts]),
               "task_ids": torch.tensor([c.task_id for c in contexts]),
               "embeddings": encoder(instructions).float().contiguous()}
    meta = {"format": FORMAT, "camera": camera, "keys": json.dumps(keys), "instructions": json.dumps(instructions),
            "context_instructions": json.dumps([c.instruction for c in contexts])}
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    os.replace(tmp, path)
    return path


def read_context_pack(path: str | Path) -> tuple[list[Context], list[str], PackedInstructions, str]:
    """(contexts, their keys, the instruction encoder over the packed embeddings, the camera)."""
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        if meta.get("format") != FORMAT:
            raise ValueError(f"{path} is not a context pack (format {meta.get('format')!r}, expected {FORMAT!r})")
        t = {k: f.get_tensor(k) for k in f.keys()}
    texts = json.loads(meta["context_instructions"])
    contexts = [Context(task_id=int(tid), instruction=s, frame=fr, proprio=p)
                for tid, s, fr, p in zip(t["task_ids"].tolist(), texts, t["frames"], t["proprio"])]
    table = dict(zip(json.loads(meta["instructions"]), t["embeddings"]))
    return contexts, json.loads(meta["keys"]), PackedInstructions(table), meta["camera"]


def main(argv: list[str] | None = None) -> Path:
    from stages.post_train_loop.training import contexts_from_episodes
    from worldenv_core.data.selection import expand_episode_paths
    from worldenv_core.models.text import InstructionEncoder

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("episodes", nargs="+", help="episode files or glob patterns")
    p.add_argument("--out", required=True)
    p.add_argument("--camera", default="agentview", help="the camera the world model imagines")
    p.add_argument("--mid-frames", type=int, default=0,
                   help="as rl.mid_episode_frames: 0 = each episode's first frame, n = n frames part way through")
    args = p.parse_args(argv)
    paths = expand_episode_paths(args.episodes)
    contexts, starts = contexts_from_episodes(paths, args.camera, args.mid_frames)
    out = write_context_pack(args.out, contexts, [st.key for st in starts], InstructionEncoder(), args.camera)
    print(f"{out}: {len(contexts)} contexts from {len(paths)} episodes, {out.stat().st_size / 2**20:.1f} MiB")
    return out


if __name__ == "__main__":
    main()
