"""The instant reflector R(o_{1:t}, g) in [0, 1] (paper sec. 4.2, appendix B.3): the probability
that instruction g has been completed by frame t.

frames -> per-frame encoder (FiLM-conditioned on the instruction; any backbone from
backbones.py, chosen with `_target_`) -> uniform sub-sample of at most `max_frames` frames ->
temporal transformer with an instruction token -> reward head -> sigmoid.

Every frame is encoded on its own (no batch statistics, no cross-frame layers before the
aggregator), so a rollout's per-frame features can be cached and the prefix re-scored after each
chunk at the cost of the aggregator alone: `IncrementalScorer` does exactly that, and its scores
equal scoring the whole prefix from scratch.
"""

from __future__ import annotations

import torch
from torch import nn

from worldenv_core.models.policy import mlp


def subsample_indices(n: int, max_frames: int) -> torch.Tensor:
    """Indices of at most `max_frames` frames spread uniformly over n, first and last included."""
    if n <= max_frames:
        return torch.arange(n)
    return torch.linspace(0, n - 1, max_frames).round().long()


class Reflector(nn.Module):
    """The trained reward head. Like every reward model (`vlm_reward.VLMYesNoReward` too) it offers
    `scorer(instructions, encoder)` for growing rollouts and `score_prefixes(frames, instruction,
    steps, encoder)` for a recorded video.

    Args:
        frame_encoder: maps {camera: (B, 3, H, W) float [0, 1]} and the instruction (B, C) to (B, D).
        camera: the camera it watches (the world simulator's camera, so imagined video can be scored).
        input_size: frames are resized to this many pixels first (None: as given); success is
            visible at low resolution and the encoder's cost falls with the square of the size.
        max_frames: frames the aggregator sees (uniformly sub-sampled from the prefix; paper: 32).
        freeze_encoder: train the aggregator and head only (a pretrained backbone, as the paper's
            frozen LLaVA).
    """

    def __init__(self, frame_encoder: nn.Module, camera: str = "agentview", input_size: int | None = 64,
                 max_frames: int = 32, d_model: int = 128, layers: int = 2, heads: int = 4,
                 instruction_dim: int = 384, freeze_encoder: bool = False):
        super().__init__()
        self.camera, self.input_size, self.max_frames = camera, input_size, int(max_frames)
        self.instruction_dim = int(instruction_dim)
        self.frame_encoder = frame_encoder.requires_grad_(not freeze_encoder)
        self.frame_proj = nn.Sequential(nn.Linear(frame_encoder.out_dim, d_model), nn.LayerNorm(d_model))
        self.lang_token = nn.Linear(instruction_dim, d_model)
        # position counted back from the newest frame: the newest frame is what success is judged on
        self.position = nn.Embedding(self.max_frames, d_model)
        layer = nn.TransformerEncoderLayer(d_model, heads, 2 * d_model, dropout=0.0, batch_first=True, norm_first=True)
        self.temporal = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.head = mlp(2 * d_model, d_model, 1, layers=1)

    def encode_frames(self, frames: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """frames (N, 3, H, W) uint8 or float in [0, 1], instruction (N, C) -> features (N, d_model)."""
        x = frames.float() / 255.0 if frames.dtype == torch.uint8 else frames.float()
        if self.input_size and x.shape[-1] != self.input_size:
            x = nn.functional.interpolate(x, size=(self.input_size, self.input_size), mode="area")
        return self.frame_proj(self.frame_encoder({self.camera: x}, instruction))

    def aggregate(self, feats: torch.Tensor, mask: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """feats (B, F, D) oldest first, right-padded; mask (B, F) True on real frames -> logits (B,).
        F <= max_frames (callers sub-sample first)."""
        b, f, _ = feats.shape
        lengths = mask.sum(1)
        back = (lengths[:, None] - 1 - torch.arange(f, device=feats.device)[None]).clamp(min=0)
        tokens = torch.cat([self.lang_token(instruction)[:, None], feats + self.position(back)], dim=1)
        pad = torch.cat([torch.zeros(b, 1, dtype=torch.bool, device=mask.device), ~mask], dim=1)
        out = self.temporal(tokens, src_key_padding_mask=pad)
        newest = out[torch.arange(b, device=feats.device), lengths]  # token 0 is the instruction
        return self.head(torch.cat([out[:, 0], newest], dim=-1)).squeeze(-1)

    def forward(self, frames: torch.Tensor, mask: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """frames (B, F, 3, H, W) already sub-sampled, right-padded; mask (B, F) -> logits (B,)."""
        b, f = mask.shape
        lang = instruction[:, None].expand(b, f, -1)
        feats = torch.zeros(b, f, self.frame_proj[0].out_features, device=frames.device)
        feats[mask] = self.encode_frames(frames[mask], lang[mask])  # padding is never encoded
        return self.aggregate(feats, mask, instruction)

    reward_kind = "trained head"  # what the experiment report calls it

    def scorer(self, instructions: list[str], encoder) -> "IncrementalScorer":
        """An incremental scorer of a batch of growing videos, one instruction each."""
        return IncrementalScorer(self, encoder(list(instructions)).to(self.lang_token.weight.device))

    def score_prefixes(self, frames: torch.Tensor, instruction, steps, encoder=None) -> torch.Tensor:
        """R at each of `steps` of one video; `instruction` as text (embedded with `encoder`) or embedded."""
        if isinstance(instruction, str):
            instruction = encoder([instruction])[0].to(self.lang_token.weight.device)
        return score_prefixes(self, frames, instruction, steps)

    @torch.no_grad()
    def score_video(self, frames: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """R for one whole prefix: frames (T, 3, H, W), instruction (C,) -> probability (scalar)."""
        idx = subsample_indices(frames.shape[0], self.max_frames)
        feats = self.encode_frames(frames[idx], instruction[None].expand(len(idx), -1))[None]
        mask = torch.ones(1, len(idx), dtype=torch.bool, device=feats.device)
        return torch.sigmoid(self.aggregate(feats, mask, instruction[None]))[0]


class IncrementalScorer:
    """Scores a batch of growing videos after every new frame (or chunk of frames) without
    re-encoding the past: per-frame features are cached, only the aggregator runs again."""

    def __init__(self, model: Reflector, instruction: torch.Tensor):
        self.model = model.eval()
        self.instruction = instruction  # (B, C)
        self.feats: list[torch.Tensor] = []  # per frame, (B, D)
        self.first: torch.Tensor | None = None  # (B,) each video's first real frame where histories differ in length

    @torch.no_grad()
    def add_history(self, histories: list) -> None:
        """Before the first `add`: each video's frames before its first one ((n_b, 3, H, W) oldest first, or None),
        judged as part of its prefix (a rollout started mid-episode, its recorded past). Shorter histories are
        left-padded and masked, so every video's score is its own prefix's."""
        if self.feats:
            raise RuntimeError("add_history() comes before the first add()")
        if len(histories) != len(self.instruction):
            raise ValueError(f"{len(histories)} histories for {len(self.instruction)} videos")
        n = [0 if h is None else len(h) for h in histories]
        if not max(n, default=0):
            return
        frames = torch.cat([h for h in histories if h is not None and len(h)])
        lang = torch.cat([self.instruction[b:b + 1].expand(k, -1) for b, k in enumerate(n) if k])
        f = self.model.encode_frames(frames, lang)
        width = max(n)
        padded = f.new_zeros(len(n), width, f.shape[-1])
        rows = iter(f.split([k for k in n if k]))
        for b, k in enumerate(n):
            if k:
                padded[b, width - k:] = next(rows)
        self.feats = list(padded.unbind(1))
        self.first = torch.tensor([width - k for k in n])

    @torch.no_grad()
    def add(self, frames: torch.Tensor) -> None:
        """frames (B, 3, H, W) for one time step, or (B, n, 3, H, W) for n consecutive ones."""
        if frames.dim() == 4:
            frames = frames[:, None]
        b, n = frames.shape[:2]
        lang = self.instruction[:, None].expand(b, n, -1).reshape(b * n, -1)
        f = self.model.encode_frames(frames.flatten(0, 1), lang).view(b, n, -1)
        self.feats += list(f.unbind(1))

    @torch.no_grad()
    def score(self) -> torch.Tensor:
        """-> (B,) R(o_{1:t}, g) of every video's prefix so far."""
        if not self.feats:
            raise RuntimeError("add() at least one frame before score()")
        if self.first is not None and bool(self.first.any()):
            return self._score_ragged()
        idx = subsample_indices(len(self.feats), self.model.max_frames).tolist()
        feats = torch.stack([self.feats[i] for i in idx], dim=1)
        mask = torch.ones(feats.shape[:2], dtype=torch.bool, device=feats.device)
        return torch.sigmoid(self.model.aggregate(feats, mask, self.instruction))

    def _score_ragged(self) -> torch.Tensor:
        """score() where videos start at different frames: each its own sub-sample, right-padded and masked."""
        all_feats = torch.stack(self.feats, dim=1)  # (B, T, D)
        picks = [int(f) + subsample_indices(len(self.feats) - int(f), self.model.max_frames) for f in self.first]
        width = max(len(p) for p in picks)
        batch = all_feats.new_zeros(len(picks), width, all_feats.shape[-1])
        mask = torch.zeros(len(picks), width, dtype=torch.bool, device=all_feats.device)
        for b, p in enumerate(picks):
            batch[b, : len(p)], mask[b, : len(p)] = all_feats[b, p.to(all_feats.device)], True
        return torch.sigmoid(self.model.aggregate(batch, mask, self.instruction))


@torch.no_grad()
def score_prefixes(model: Reflector, frames: torch.Tensor, instruction: torch.Tensor, steps) -> torch.Tensor:
    """R at each of `steps` (increasing frame indices) of one video (T+1, 3, H, W), seeing only
    the frames at those steps, as a rollout scored after every chunk does -> (len(steps),).
    Each frame is encoded once; all prefixes go through the aggregator as one padded batch."""
    chosen = frames[torch.as_tensor(list(steps))]
    n = len(chosen)
    feats = model.encode_frames(chosen, instruction[None].expand(n, -1))
    picks = [subsample_indices(j + 1, model.max_frames) for j in range(n)]
    width = max(len(p) for p in picks)
    batch = feats.new_zeros(n, width, feats.shape[-1])
    mask = torch.zeros(n, width, dtype=torch.bool, device=feats.device)
    for j, p in enumerate(picks):
        batch[j, : len(p)], mask[j, : len(p)] = feats[p], True
    return torch.sigmoid(model.aggregate(batch, mask, instruction[None].expand(n, -1)))
