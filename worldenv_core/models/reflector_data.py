"""Training prefixes for the reflector, with balanced sampling.

A prefix ending at frame t shows what a chunked rollout has at that point: the frames at
t, t - K, t - 2K, ... and the first frame, uniformly sub-sampled to the model's `max_frames`.
Its label is y_t (1 from the oracle's first success onward), or with `label_delay` d > 0 the
settled label: 1 from d steps after the first success. The oracle reports a pick-and-place done
the moment the object touches its target, still in the gripper, and that frame looks like a
failed rollout holding the object just above the target; a reflector trained on settled labels
waits for the release, stops a few steps later and stops far less often on such near misses.
Positives are rare (a demo that stops at success has one positive frame), so each batch draws half positives and half
negatives; `hard_negative_fraction` of the negatives come from the last `hard_window` frames
before a success, where a premature stop would cost an episode, plus (when mining is on)
the negatives the model itself currently scores highest: the near misses of failed rollouts,
which look almost like success and are what false stops are made of.
"""

from __future__ import annotations

import numpy as np
import torch

from worldenv_core.models.reflector import subsample_indices
from worldenv_core.rl.termination import success_labels


def settled_labels(success: np.ndarray, delay: int = 0) -> np.ndarray:
    """Per-frame oracle flags -> training labels: 1 from `delay` steps after the first success
    onward (from the last frame at the latest, so a successful episode keeps a positive)."""
    y = success_labels(success)
    if delay > 0 and y.any():
        onset = min(int(np.argmax(y)) + delay, len(y) - 1)
        y = y.copy()
        y[:onset] = False
    return y


def prefix_frames(t: int, stride: int, max_frames: int) -> np.ndarray:
    """Frame indices a chunked rollout has at frame t (oldest first), sub-sampled."""
    idx = np.arange(t, -1, -stride)[::-1]
    if idx[0] != 0:
        idx = np.r_[0, idx]
    return idx[subsample_indices(len(idx), max_frames).numpy()]


class PrefixSampler:
    """Seeded balanced batches of (frames, mask, label, instruction) from in-memory episodes."""

    def __init__(self, episodes, camera: str, stride: int, max_frames: int, hard_negative_fraction: float = 0.25,
                 hard_window: int = 16, label_delay: int = 0):
        self.frames = [ep.video(camera) for ep in episodes]
        self.instructions = [ep.meta.instruction for ep in episodes]
        self.max_frames = int(max_frames)
        # `stride`, `label_delay` and `hard_window` are in simulator steps; an episode recorded only at
        # its checks (a paired rollout: `steps_per_frame` = the chunk) counts them in its own frames
        per = [int(ep.steps_per_frame) for ep in episodes]
        self.strides = [max(1, int(stride) // k) for k in per]
        self.labels = [settled_labels(ep.success, -(-label_delay // k)) for ep, k in zip(episodes, per)]
        pos, neg, hard = [], [], []
        for i, y in enumerate(self.labels):
            for t in range(len(y)):
                (pos if y[t] else neg).append((i, t))
            if y.any():
                ts = int(np.argmax(y))
                hard += [(i, t) for t in range(max(0, ts - -(-hard_window // per[i])), ts)]
        if not pos or not neg:
            raise ValueError(f"the reflector needs successful and unsuccessful frames; got {len(pos)} positive "
                             f"and {len(neg)} negative frames from {len(episodes)} episodes")
        self.pos, self.neg, self.hard = np.array(pos), np.array(neg), np.array(hard or neg)
        self.window_hard = self.hard
        self.hard_fraction = float(hard_negative_fraction)

    def set_mined(self, mined) -> None:
        """Hard negatives are the pre-success window plus these (episode, frame) pairs."""
        mined = np.asarray(mined, dtype=np.int64).reshape(-1, 2)
        self.hard = np.concatenate([self.window_hard, mined]) if len(mined) else self.window_hard

    def mine(self, scores_fn, threshold: float) -> np.ndarray:
        """Negative prefix ends (at the chunk boundaries a rollout is scored at) that
        `scores_fn(episode index, frames, steps) -> R per step` puts above `threshold`, each
        with the stride - 1 frames before it (the prefixes ending there look the same)."""
        out = []
        for i, frames in enumerate(self.frames):
            stride = self.strides[i]
            steps = np.arange(0, len(frames), stride)
            steps = steps[~self.labels[i][steps]]
            if not len(steps):
                continue
            high = steps[np.asarray(scores_fn(i, frames, steps.tolist())) > threshold]
            out += [(i, t) for s in high for t in range(max(0, s - stride + 1), s + 1) if not self.labels[i][t]]
        return np.array(out, dtype=np.int64).reshape(-1, 2)

    def counts(self) -> dict:
        return {"positive_frames": len(self.pos), "negative_frames": len(self.neg), "hard_negative_frames": len(self.hard)}

    def batch(self, batch_size: int, seed: int) -> dict:
        """One balanced batch; the same seed gives the same batch (resume is exact)."""
        rng = np.random.default_rng(seed)
        n_pos = batch_size // 2
        n_hard = int(round((batch_size - n_pos) * self.hard_fraction))
        picks = [self.pos[rng.integers(len(self.pos), size=n_pos)],
                 self.hard[rng.integers(len(self.hard), size=n_hard)],
                 self.neg[rng.integers(len(self.neg), size=batch_size - n_pos - n_hard)]]
        items = np.concatenate(picks)
        labels = torch.tensor([1.0] * n_pos + [0.0] * (batch_size - n_pos))
        return {**self.gather(items), "label": labels}

    def gather(self, items) -> dict:
        seqs = [prefix_frames(int(t), self.strides[int(i)], self.max_frames) for i, t in items]
        f = max(len(s) for s in seqs)
        first = self.frames[0]
        frames = torch.zeros(len(items), f, *first.shape[1:], dtype=first.dtype)
        mask = torch.zeros(len(items), f, dtype=torch.bool)
        for b, ((i, _), s) in enumerate(zip(items, seqs)):
            frames[b, : len(s)] = self.frames[int(i)][torch.from_numpy(s)]
            mask[b, : len(s)] = True
        return {"frames": frames, "mask": mask, "instruction": [self.instructions[int(i)] for i, _ in items]}
