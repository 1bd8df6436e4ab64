"""A step measured on some tasks, kept off the others: the policy's mean actions on recorded frames of the tasks
a step was not measured on are pulled back to what they were before it, those of the tasks it was measured on
held where the step took them.

Why: one ES step per task (`rl=es_by_task`) lifts the task it was measured on and moves every other task's actions
too, by chance and by shared weights; on libero_spatial the full-budget run lifted four tasks by 20-62 points and
cost two others 14-38 (results/rl_campaign.md), and the same update twice as long lifted the stepped tasks again and
cost the others more. The step's effect on a task it never measured is a random move for that task: this keeps it
out, on the states the task's recorded frames show (its demos), with a few gradient steps on the squared
difference of mean action chunks, in the normalised units the policy emits. Nothing is rolled out: frames only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from worldenv_core.rl import es


@dataclass
class AnchorFrames:
    """Recorded frames as the policy reads them, with each frame's task."""
    images: dict[str, torch.Tensor]  # camera -> (N, 3, H, W) uint8
    proprio: torch.Tensor            # (N, P)
    instruction: torch.Tensor        # (N, E): the instruction's embedding
    task_ids: torch.Tensor           # (N,) int64

    def __len__(self) -> int:
        return len(self.task_ids)

    def rows(self, idx) -> tuple:
        return {c: v[idx] for c, v in self.images.items()}, self.proprio[idx], self.instruction[idx]


def anchor_frames(files: list, cameras: list[str], encode: Callable[[list[str]], torch.Tensor],
                  every: int = 8) -> AnchorFrames:
    """Every `every`-th frame (the policy reads one frame per chunk of 8) of the recorded episodes in `files`,
    each episode read and its instruction encoded once."""
    from worldenv_core.data.mcap_io import read_episode

    if not files:
        raise ValueError("anchor frames need at least one recorded episode")
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
    return AnchorFrames({c: torch.cat(v) for c, v in images.items()}, torch.cat(proprio), torch.cat(instruction),
                        torch.cat(tasks))


@torch.no_grad()
def mean_actions(policy: torch.nn.Module, frames: AnchorFrames, batch: int = 256) -> torch.Tensor:
    """The policy's mean action chunk on every frame, (N, chunk, action_dim)."""
    return torch.cat([policy(*frames.rows(slice(i, i + batch)))[0] for i in range(0, len(frames), batch)])


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt()) if x.numel() else float("nan")


def anchored_step(policy: torch.nn.Module, step: Callable[[torch.nn.Module], dict], frames: AnchorFrames,
                  own_tasks, which: str = "mean", iterations: int = 200, lr: float = 1e-4, batch: int = 128,
                  seed: int = 0) -> dict:
    """`step(policy)` (in place), then `iterations` Adam steps on the parameters ES moves (`which`) pulling the
    mean actions on frames of tasks outside `own_tasks` back to their values before the step and holding those of
    `own_tasks` at their values after it. -> the step's figures with how much of its action change on each side
    is left (`anchor_left_other`: near 0 removes it from the others) and how far the own tasks' actions ended from
    where the step took them (`anchor_own_error`, relative to the step's own change: near 0 keeps its effect)."""
    own = torch.isin(frames.task_ids, torch.as_tensor(sorted(set(int(t) for t in own_tasks)), dtype=torch.int64))
    was_training = policy.training
    policy.eval()
    before = mean_actions(policy, frames)
    stats = dict(step(policy))
    after = mean_actions(policy, frames)
    target = torch.where(own[:, None, None], after, before)
    moved_own, moved_other = _rms((after - before)[own]), _rms((after - before)[~own])
    params = [p for _, p in es.es_parameters(policy, which)]
    if (~own).any() and iterations > 0:
        opt = torch.optim.Adam(params, lr=lr)
        g = torch.Generator().manual_seed(seed)
        for _ in range(iterations):
            idx = torch.randint(len(frames), (min(batch, len(frames)),), generator=g)
            loss = (policy(*frames.rows(idx))[0] - target[idx]).pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        for p in policy.parameters():
            p.grad = None
    final = mean_actions(policy, frames)
    policy.train(was_training)
    return {**stats, "anchor_moved_own": moved_own, "anchor_moved_other": moved_other,
            "anchor_left_other": _rms((final - before)[~own]) / moved_other if moved_other else float("nan"),
            "anchor_own_error": _rms((final - after)[own]) / moved_own if moved_own else float("nan")}
