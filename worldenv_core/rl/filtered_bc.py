"""Success-filtered behaviour cloning: the policy imitates its own successful rollouts.

LOOP's PPO step on a batch is bounded (a clip, a trust region) and follows the batch's policy
gradient; for this project's Laplace policy that gradient was measured to be noise at every batch
size the real route affords (docs/notebook/rl_recipe.md: a pooled signal of 0.24 against a noise of
185 per mixed group over 1,536 real episodes). The successes themselves carry more: each is a
complete trajectory that worked from a start the demonstrations never showed. Filtered behaviour
cloning (RWR with a 0/1 reward; RoboCat's and iRe-VLA's self-improvement) keeps every successful
rollout of every iteration in a buffer and fits the policy's mean to its executed chunks with the
SFT loss (L1 on mu, paper eq. 6), many steps per iteration, as SFT would with more demonstrations.
The rollouts, the verdicts (oracle or reflector) and the accounting are LOOP's; only the update
differs (`rl.policy_update=filtered_bc`).

The buffer lives in the run's work dir, one file per iteration, named by what drew the iteration,
so a resumed iteration rewrites its own file instead of adding a second copy.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from worldenv_core.training import random_shift

_FIELDS = ("frames", "proprio", "instruction", "actions", "mask")


class SuccessBuffer:
    """The chunks of every successful rollout so far: frames (n, 3, H, W) uint8, proprio (n, P),
    instruction (n, D), actions (n, K, A) in the policy's normalised space, mask (n, K) of the steps
    executed. `folder` None keeps it in memory only (a timing probe)."""

    def __init__(self, folder: str | Path | None):
        self.folder = Path(folder) if folder is not None else None
        self.parts: dict[str, dict[str, torch.Tensor]] = {}
        if self.folder is not None and self.folder.is_dir():
            for f in sorted(self.folder.glob("*.pt")):
                self.parts[f.stem] = torch.load(f, weights_only=True)

    def add(self, key: str, batch) -> int:
        """The successful rollouts of `batch` (a `RolloutBatch`), under `key` (replacing an earlier
        part of that key). -> the number of rollouts added."""
        wins = batch.by_reflector.bool().cpu()
        live = batch.mask[..., 0].cpu()[wins] > 0  # (W, C): the chunks those rollouts took
        rows, cols = live.nonzero(as_tuple=True)
        take = lambda x: x.detach().cpu()[wins][rows, cols]  # noqa: E731
        part = {"frames": take(batch.frames), "proprio": take(batch.proprio),
                "instruction": batch.instruction.detach().cpu()[wins][rows], "actions": take(batch.actions),
                "mask": take(batch.mask)}
        part["rollouts"] = torch.tensor(int(wins.sum()))
        self.parts[key] = part
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            tmp = self.folder / f".{key}.pt.tmp"
            torch.save(part, tmp)
            os.replace(tmp, self.folder / f"{key}.pt")  # whole or absent: a resume never reads half a part
        return int(wins.sum())

    def remove(self, key: str) -> None:
        """Drop the part `key` (an update the paired-replay guard undid: its imagined successes are suspect)."""
        self.parts.pop(key, None)
        if self.folder is not None:
            (self.folder / f"{key}.pt").unlink(missing_ok=True)

    @property
    def rollouts(self) -> int:
        return sum(int(p["rollouts"]) for p in self.parts.values())

    def __len__(self) -> int:
        return sum(len(p["frames"]) for p in self.parts.values())

    def tensors(self) -> dict[str, torch.Tensor]:
        """Every part's chunks, concatenated (in key order: the same on a resume)."""
        parts = [self.parts[k] for k in sorted(self.parts)]
        return {f: torch.cat([p[f] for p in parts]) for f in _FIELDS}


def bc_update(policy, optimizer, buffer: SuccessBuffer, steps: int, minibatch: int,
              generator: torch.Generator | None = None, augment_shift: int = 0) -> dict:
    """`steps` Adam steps of L1 on the mean over minibatches of the buffer's chunks (uniform, with
    replacement across steps), the executed steps only, images shifted by up to `augment_shift`
    pixels as in SFT. -> the first and the last minibatch's loss, the steps, the buffer's size."""
    if steps < 1 or minibatch < 1:
        raise ValueError(f"filtered BC needs steps >= 1 and minibatch >= 1, got {steps} and {minibatch}")
    if not len(buffer):
        return {"bc_steps": 0, "buffer_rollouts": 0, "buffer_chunks": 0}
    data = buffer.tensors()
    dev = next(policy.parameters()).device
    params = [p for g in optimizer.param_groups for p in g["params"]]
    losses = []
    policy.train()  # as SFT trains it (ACT's dropout included)
    for _ in range(steps):
        idx = torch.randint(len(data["frames"]), (minibatch,), generator=generator)
        frames = data["frames"][idx].to(dev)
        if augment_shift:
            frames = random_shift(frames, augment_shift, generator)
        mu, _ = policy({policy.cameras[0]: frames}, data["proprio"][idx].to(dev), data["instruction"][idx].to(dev))
        valid = data["mask"][idx].to(dev)[..., None]
        loss = ((mu - data["actions"][idx].to(dev)).abs() * valid).sum() / (valid.sum().clamp(min=1) * mu.shape[-1])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        losses.append(loss.item())
    policy.eval()
    return {"bc_steps": steps, "bc_loss_first": losses[0], "bc_loss": sum(losses[-10:]) / len(losses[-10:]),
            "buffer_rollouts": buffer.rollouts, "buffer_chunks": len(buffer)}
