"""Training data for the world simulator's flow model, in latent space.

Once the autoencoder is trained, every frame of every episode is encoded once; the flow model
then trains on chunks sliced from those latents (no image decoding or encoding per step), with
action maps drawn from the recorded next states s_{t+1..t+K} (teacher forcing; at imagination
time the kinematic model supplies them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch.utils.data import Dataset

if TYPE_CHECKING:  # not at run time: the episode package imports MCAP, which a latent pack's GPU host lacks
    from worldenv_core.data.episode import Episode


@torch.no_grad()
def encode_episode_frames(model, frames: np.ndarray, batch: int = 64, device="cpu") -> torch.Tensor:
    """(T, H, W, 3) uint8 -> unscaled latents (T, C, h, w) on the CPU."""
    x = torch.from_numpy(frames).permute(0, 3, 1, 2)
    out = [model.autoencoder.encode(x[i:i + batch].to(device)).cpu() for i in range(0, len(x), batch)]
    return torch.cat(out)


DEMO_SOURCES = ("expert", "import")  # demonstrations, as against policy rollouts


class LatentChunks(Dataset):
    """Items at every step t of every episode: memory latents (M, C, h, w) at the model's memory
    offsets, the next K latents (K, C, h, w), the K actions and next proprio states, a validity
    mask for steps past the episode end (edge-padded), and the task id (its camera); "joints", the
    arm's joint angles at the K steps, where the episodes carry them (a model drawing the arm reads them).

    `chunks_ahead` > 1 (open-loop training) widens an item to `chunks_ahead` x K steps ahead
    ("target", "proprio", "actions", "valid" of shape (chunks_ahead * K, ...)) and adds "past", the
    real latents t - history .. t (history + 1, C, h, w) that an imagined rollout from t starts
    with; t then only runs to where the last chunk still has a step inside the episode.

    `frames` (one (T + 1, 3, H, W) uint8 tensor per episode) adds "frames", the real images of the
    steps ahead, for what learns to draw them (the refiner)."""

    def __init__(self, latents: list[torch.Tensor], episodes: list[Episode], memory_offsets, chunk: int,
                 chunks_ahead: int = 1, frames: list[torch.Tensor] | None = None):
        if chunks_ahead < 1:
            raise ValueError(f"chunks_ahead must be >= 1, got {chunks_ahead}")
        self.latents = latents
        self.proprio = [torch.from_numpy(ep.proprio) for ep in episodes]
        joints = [getattr(ep, "joint_pos", None) for ep in episodes]
        self.joints = [torch.from_numpy(j) for j in joints] if all(j is not None for j in joints) else None
        self.actions = [torch.from_numpy(ep.actions) for ep in episodes]
        self.task_ids = [ep.meta.task_id for ep in episodes]
        self.sources = [getattr(ep.meta, "source", None) for ep in episodes]
        self.frames = frames
        self.offsets = np.asarray(memory_offsets)
        self.chunk, self.ahead = chunk, chunks_ahead
        lead = chunk * (chunks_ahead - 1)  # steps before the last chunk
        self.index = [(e, t) for e, ep in enumerate(episodes) for t in range(max(0, ep.length - lead))]

    def __len__(self) -> int:
        return len(self.index)

    def demo_weights(self, share: float) -> torch.Tensor:
        """Per-item sampling weights (for `batches`) under which a drawn item comes from a demonstration
        (an expert or imported episode) with probability `share` and from a policy rollout otherwise,
        uniformly within each; with only one kind of episode, uniform. Exploration rollouts outnumber
        the demos, and a one-step flow model trained on many grasps that split between lift and
        miss learns their mean (a fading bowl): drawing the demos more often keeps the clean grasp."""
        if not 0 < share < 1:
            raise ValueError(f"demo_share must be strictly between 0 and 1, got {share}")
        if None in self.sources:
            raise ValueError("demo_share needs each episode's source, which this data does not carry (a latent pack "
                             "written before sources were kept: pack again)")
        demo = torch.tensor([self.sources[e] in DEMO_SOURCES for e, _ in self.index])
        n_demo = int(demo.sum())
        if n_demo in (0, len(demo)):
            return torch.ones(len(demo))
        return torch.where(demo, share / n_demo, (1 - share) / (len(demo) - n_demo))

    def __getitem__(self, i: int) -> dict:
        e, t = self.index[i]
        z, T = self.latents[e], len(self.actions[e])
        mem = torch.from_numpy(np.clip(t - self.offsets, 0, None))
        fut = np.arange(t + 1, t + 1 + self.chunk * self.ahead)
        valid = fut <= T
        fut_idx = torch.from_numpy(np.clip(fut, 0, T))
        act_idx = torch.from_numpy(np.clip(fut - 1, 0, T - 1))
        item = {"memory": z[mem], "target": z[fut_idx], "proprio": self.proprio[e][fut_idx],
                "actions": self.actions[e][act_idx], "valid": torch.from_numpy(valid), "task_id": self.task_ids[e]}
        if self.joints is not None:
            item["joints"] = self.joints[e][fut_idx]
        if self.frames is not None:
            item["frames"] = self.frames[e][fut_idx]
        if self.ahead > 1:
            item["past"] = z[torch.arange(t - int(self.offsets.max()), t + 1).clamp(min=0)]
        return item
