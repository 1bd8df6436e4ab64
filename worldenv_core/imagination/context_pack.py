"""A context pack: imagined LOOP's contexts as one safetensors file, so that `post_train_loop
contexts_from=<pack>` runs on a machine that has neither the episodes, the simulator nor the
instruction encoder's weights (a rented GPU). Imagined LOOP needs of an episode only the frame,
proprio and instruction it starts from (and a mid-episode frame's recorded past, which the reward
model is shown): the pack holds those (frames as uint8, 49 KB each at 128 px), each instruction's
embedding by the encoder the policy was trained with, where each
context came from, the task contract it was chosen under and the settings that chose it.
`post_train_loop contexts_to=<pack>` writes one from exactly the contexts the stage would train on."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from worldenv_core.imagination.env import Context
from worldenv_core.packs import open_pack, write_pack

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


@dataclass
class ContextPack:
    contexts: list[Context]
    keys: list[str]              # where each context came from (episode key and frame)
    encoder: PackedInstructions
    camera: str
    task: dict                   # the task contract's meta (TaskContract.meta) it was chosen under
    settings: dict               # what chose the contexts (e.g. mid_episode_frames)


def write_context_pack(path: str | Path, contexts: list[Context], keys: list[str], encoder, camera: str,
                       task: dict, settings: dict | None = None) -> Path:
    """The contexts and one embedding per distinct instruction, written to a temporary name and
    renamed when complete."""
    if not contexts or len(contexts) != len(keys):
        raise ValueError(f"a pack needs one key per context: {len(contexts)} contexts, {len(keys)} keys")
    instructions = sorted({c.instruction for c in contexts})
    tensors = {"frames": torch.stack([c.frame for c in contexts]).contiguous(),
               "proprio": torch.stack([torch.as_tensor(c.proprio, dtype=torch.float64) for c in contexts]),
               "task_ids": torch.tensor([c.task_id for c in contexts]),
               "embeddings": encoder(instructions).float().contiguous()}
    if all(c.joint_pos is not None for c in contexts):  # what a world model that draws the arm starts from
        tensors["joint_pos"] = torch.stack([torch.as_tensor(c.joint_pos, dtype=torch.float64) for c in contexts])
    lengths = [0 if c.history is None else len(c.history) for c in contexts]
    if any(lengths):  # mid-episode contexts' recorded pasts for the reward model, concatenated
        tensors["history"] = torch.cat([c.history for c in contexts if c.history is not None]).contiguous()
        tensors["history_lengths"] = torch.tensor(lengths)
    meta = {"format": FORMAT, "camera": camera, "keys": json.dumps(keys), "instructions": json.dumps(instructions),
            "context_instructions": json.dumps([c.instruction for c in contexts]), "task": json.dumps(task),
            "settings": json.dumps(settings or {})}
    return write_pack(path, tensors, meta)


def read_context_pack(path: str | Path) -> ContextPack:
    with open_pack(path, FORMAT, "a context pack",
                   f"python -m stages.post_train_loop +task=<task> contexts_to={path}") as (f, meta):
        t = {k: f.get_tensor(k) for k in f.keys()}
    texts = json.loads(meta["context_instructions"])
    lengths = t["history_lengths"].tolist() if "history_lengths" in t else [0] * len(texts)
    pasts = iter(t["history"].split([k for k in lengths if k])) if any(lengths) else iter(())
    joints = t["joint_pos"] if "joint_pos" in t else [None] * len(texts)
    contexts = [Context(task_id=int(tid), instruction=s, frame=fr, proprio=p, history=next(pasts) if k else None,
                        joint_pos=q)
                for tid, s, fr, p, k, q in zip(t["task_ids"].tolist(), texts, t["frames"], t["proprio"], lengths, joints)]
    table = dict(zip(json.loads(meta["instructions"]), t["embeddings"]))
    return ContextPack(contexts, json.loads(meta["keys"]), PackedInstructions(table), meta["camera"],
                       json.loads(meta.get("task", "{}")), json.loads(meta.get("settings", "{}")))
