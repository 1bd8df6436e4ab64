"""Recorded frames as the policy reads them (one camera image per chunk, the proprio, the instruction's
embedding), with each frame's task, and the policy's mean action chunks on them: what the tools that compare
policies' actions (`random_update --frames`, `update_similarity`) and the anchored replay read."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch


@dataclass
class PolicyFrames:
    """Recorded frames as the policy reads them, with each frame's task."""
    images: dict[str, torch.Tensor]  # camera -> (N, 3, H, W) uint8
    proprio: torch.Tensor            # (N, P)
    instruction: torch.Tensor        # (N, E): the instruction's embedding
    task_ids: torch.Tensor           # (N,) int64

    def __len__(self) -> int:
        return len(self.task_ids)

    def rows(self, idx) -> tuple:
        return {c: v[idx] for c, v in self.images.items()}, self.proprio[idx], self.instruction[idx]


def policy_frames(files: list, cameras: list[str], encode: Callable[[list[str]], torch.Tensor],
                  every: int = 8) -> PolicyFrames:
    """Every `every`-th frame (the policy reads one frame per chunk of 8) of the recorded episodes in `files`,
    each episode read and its instruction encoded once."""
    from worldenv_core.data.mcap_io import read_episode

    if not files:
        raise ValueError("policy frames need at least one recorded episode")
    images: dict[str, list] = {c: [] for c in cameras}
    proprio, instruction, tasks = [], [], []
    for file in files:
        episode = read_episode(file, cameras=cameras)
        frames = np.arange(0, len(episode.proprio), every)
        for c in cameras:
            images[c].append(episode.video(c)[frames])
        proprio.append(torch.as_tensor(episode.proprio[frames], dtype=torch.float32))
        instruction.append(encode([episode.meta.instruction]).expand(len(frames), -1))
        tasks.append(torch.full((len(frames),), episode.meta.task_id, dtype=torch.int64))
    return PolicyFrames({c: torch.cat(v) for c, v in images.items()}, torch.cat(proprio), torch.cat(instruction),
                        torch.cat(tasks))


@torch.no_grad()
def mean_actions(policy: torch.nn.Module, frames: PolicyFrames, batch: int = 256) -> torch.Tensor:
    """The policy's mean action chunk on every frame, (N, chunk, action_dim)."""
    return torch.cat([policy(*frames.rows(slice(i, i + batch)))[0] for i in range(0, len(frames), batch)])
