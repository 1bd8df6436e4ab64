"""The action-conditioned world simulator (World-Env sec. 4.1, appendix B.2; EVAC-style).

Given memory frames (the current frame and a few sparse earlier ones) and the K action maps of
the chunk ahead, predict the K next frames. Generation is the paper's bottleneck, so:

* everything generative happens in the latent space of a small convolutional autoencoder
  (16x16x4 latents by default), where a pass costs a fraction of a pixel-space pass;
* the K frames of a chunk are predicted in parallel (one network call for B rollouts x K
  frames), each conditioned on the shared memory, its own action map and its index in the chunk;
* the generator is a rectified-flow velocity network sampled with a few Euler steps (1-4),
  predicting the change from the current latent, so "nothing moves" is the zero-effort answer;
* memory stays in latent space across chunks: imagined frames are never re-encoded, and pixels
  are decoded only for what a caller keeps.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from worldenv_core.distributed import random_rows


def _groups(ch: int) -> int:
    return math.gcd(8, ch)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice, with an optional FiLM (scale, shift) from an embedding."""

    def __init__(self, c_in: int, c_out: int, emb_dim: int = 0):
        super().__init__()
        self.norm1, self.conv1 = nn.GroupNorm(_groups(c_in), c_in), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm2, self.conv2 = nn.GroupNorm(_groups(c_out), c_out), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.film = nn.Linear(emb_dim, 2 * c_out) if emb_dim else None
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.norm2(h)
        if self.film is not None:
            scale, shift = self.film(emb)[:, :, None, None].chunk(2, dim=1)
            h = h * (1 + scale) + shift
        return self.skip(x) + self.conv2(F.silu(h))


class Autoencoder(nn.Module):
    """uint8 images (N, 3, H, W) <-> latents (N, C, H/f, W/f). A `patch` x `patch` patchify stem
    keeps full-resolution work to one cheap layer, and the decoder ends in a pixel shuffle for the
    same reason: decoding is what imagined rollouts pay per kept frame."""

    def __init__(self, image_size: int, latent_size: int = 16, latent_channels: int = 4, widths=(32, 64),
                 patch: int = 4):
        super().__init__()
        factor = image_size // latent_size
        if factor * latent_size != image_size or factor < patch or factor % patch or (factor // patch) & (factor // patch - 1):
            raise ValueError(f"image_size {image_size} must be latent_size {latent_size} times patch {patch} "
                             "times a power of two")
        n_down = int(math.log2(factor // patch))
        widths = list(widths)[: n_down + 1] + [widths[-1]] * max(0, n_down + 1 - len(widths))
        self.image_size, self.latent_size, self.latent_channels = image_size, latent_size, latent_channels
        enc = [nn.Conv2d(3, widths[0], patch, stride=patch)]
        for i in range(n_down):
            enc += [ResBlock(widths[i], widths[i]), nn.Conv2d(widths[i], widths[i + 1], 3, stride=2, padding=1)]
        enc += [ResBlock(widths[-1], widths[-1]), nn.GroupNorm(_groups(widths[-1]), widths[-1]), nn.SiLU(),
                nn.Conv2d(widths[-1], latent_channels, 1)]
        self.encoder = nn.Sequential(*enc)
        dec = [nn.Conv2d(latent_channels, widths[-1], 3, padding=1), ResBlock(widths[-1], widths[-1])]
        for i in reversed(range(n_down)):
            dec += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(widths[i + 1], widths[i], 3, padding=1),
                    ResBlock(widths[i], widths[i])]
        dec += [nn.GroupNorm(_groups(widths[0]), widths[0]), nn.SiLU(),
                nn.Conv2d(widths[0], 3 * patch * patch, 3, padding=1), nn.PixelShuffle(patch)]
        self.decoder = nn.Sequential(*dec)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        images = images.contiguous()  # a permuted (channels-last) view makes CPU convs several times slower
        x = images.float() / 127.5 - 1.0 if images.dtype == torch.uint8 else images * 2 - 1
        return self.encoder(x)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """-> images in [0, 1] (float)."""
        return (self.decoder(z).clamp(-1, 1) + 1) / 2


def _sinusoid(t: torch.Tensor, dim: int) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / half)
    ang = t.float()[:, None] * 1000.0 * freqs[None]
    return torch.cat([ang.sin(), ang.cos()], dim=1)


class VelocityNet(nn.Module):
    """A two-level U-Net over latents: input = noisy target latent, memory latents and the
    patch-embedded action map (channels), FiLM-conditioned on flow time, chunk index and
    (optionally) the raw action."""

    def __init__(self, latent_channels: int, memory: int, map_size: int, latent_size: int, chunk: int,
                 width: int = 64, map_channels: int = 16, action_dim: int = 7, use_raw_actions: bool = False):
        super().__init__()
        patch = map_size // latent_size
        self.map_embed = nn.Conv2d(3, map_channels, patch, stride=patch)  # action map -> latent grid
        emb = 4 * width
        self.time_mlp = nn.Sequential(nn.Linear(width, emb), nn.SiLU(), nn.Linear(emb, emb))
        self.index_emb = nn.Embedding(chunk, emb)
        self.action_mlp = nn.Sequential(nn.Linear(action_dim, emb), nn.SiLU(), nn.Linear(emb, emb)) if use_raw_actions else None
        self.width = width
        c_in = latent_channels * (1 + memory) + map_channels
        self.stem = nn.Conv2d(c_in, width, 3, padding=1)
        self.down = nn.ModuleList([ResBlock(width, width, emb), ResBlock(width, width, emb)])
        self.downsample = nn.Conv2d(width, 2 * width, 3, stride=2, padding=1)
        self.mid = nn.ModuleList([ResBlock(2 * width, 2 * width, emb), ResBlock(2 * width, 2 * width, emb)])
        self.upsample = nn.ConvTranspose2d(2 * width, width, 2, stride=2)
        self.up = nn.ModuleList([ResBlock(2 * width, width, emb), ResBlock(width, width, emb)])
        self.out = nn.Sequential(nn.GroupNorm(_groups(width), width), nn.SiLU(), nn.Conv2d(width, latent_channels, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    def forward(self, x_t, t, memory, action_map, index, action=None):
        """x_t (N, C, h, w); t (N,); memory (N, M*C, h, w); action_map (N, 3, H, W); index (N,)."""
        emb = self.time_mlp(_sinusoid(t, self.width)) + self.index_emb(index)
        if self.action_mlp is not None and action is not None:
            emb = emb + self.action_mlp(action)
        h = self.stem(torch.cat([x_t, memory, self.map_embed(action_map)], dim=1))
        for blk in self.down:
            h = blk(h, emb)
        skip = h
        h = self.downsample(h)
        for blk in self.mid:
            h = blk(h, emb)
        h = torch.cat([self.upsample(h), skip], dim=1)
        for blk in self.up:
            h = blk(h, emb)
        return self.out(h)


class ArmRefiner(nn.Module):
    """A decoded frame redrawn where the action map says the robot is (EVAC's pixel conditioning, after
    the decoder): the arm is fully determined by the proprio state the map draws, but a 16x16x4 latent
    carries it coarsely and open loop it smears into the background within a few chunks. The refiner sees
    the decoded image and the frame's action map at map resolution and adds a residual at full
    resolution; its last layer starts at zero, so an untrained refiner leaves every frame as decoded."""

    def __init__(self, image_size: int, map_size: int, width: int = 32, blocks: int = 3):
        super().__init__()
        factor = image_size // map_size
        if factor * map_size != image_size or factor < 1:
            raise ValueError(f"the refiner needs image_size {image_size} a multiple of map_size {map_size}")
        self.stem = nn.Conv2d(3, width, factor, stride=factor)  # the image to the map's grid
        self.fuse = nn.Conv2d(width + 3, width, 3, padding=1)
        self.blocks = nn.Sequential(*[ResBlock(width, width) for _ in range(blocks)])
        self.out = nn.Sequential(nn.GroupNorm(_groups(width), width), nn.SiLU(),
                                 nn.Conv2d(width, 3 * factor * factor, 3, padding=1), nn.PixelShuffle(factor))
        nn.init.zeros_(self.out[-2].weight)
        nn.init.zeros_(self.out[-2].bias)

    def forward(self, images: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
        """images (N, 3, H, W) in [0, 1], maps (N, 3, S, S) in [0, 1] -> (N, 3, H, W) in [0, 1]."""
        h = self.fuse(torch.cat([self.stem(images * 2 - 1), maps * 2 - 1], dim=1))
        return (images + self.out(self.blocks(h))).clamp(0, 1)


class WorldSimulator(nn.Module):
    """Args:
        image_size, chunk: the task contract (frames are square; K frames per call).
        memory_offsets: which past frames condition a chunk, in steps before the current one
            (0 = the current frame); EVAC's sparse memory.
        sampling_steps: Euler steps of the flow sampler at inference (1-4 keeps it fast).
        detail_gate: how imagined frames are rendered: > 0 puts the last real frame's fine detail
            back where the decoded content has not changed (worldenv_core/imagination/simulator.py); 0 off.
        noise_scale: the sampler's temperature, the scale of the noise the flow starts from. 1 draws
            samples of the learned distribution; 0 starts every rollout from the same point, and
            with one Euler step gives the flow's conditional mean (v(x0, 0) = E[x1] - x0), the
            prediction with the least squared error: sharper for metrics, no per-rollout variety.
        static_snap: open-loop drift control (worldenv_core/imagination/simulator.py): latent positions whose
            predicted change from the last real frame is below this (mean |change| over channels,
            in latent std units) are snapped back to that frame; 0 = off.
        refiner_width: > 0 adds an `ArmRefiner` of this width after the decoder (frames decoded with
            their action maps are redrawn where the robot is; trained by train_worldsim's refine phase).
        arm_map: the action maps it is conditioned on draw the arm's links under the gripper
            (`worldenv_core/kinematics/arm.py`), so the whole robot's pose is given, not inferred; its
            rollouts then need the arm's joint angles at their start.
    """

    def __init__(self, image_size: int, chunk: int = 8, memory_offsets=(0, 4, 8, 16), latent_size: int = 16,
                 latent_channels: int = 4, ae_widths=(32, 64), ae_patch: int = 4, width: int = 48,
                 map_channels: int = 16, map_size: int | None = None, use_raw_actions: bool = False,
                 sampling_steps: int = 4, action_dim: int = 7, detail_gate: float = 0.0, noise_scale: float = 1.0,
                 static_snap: float = 0.0, refiner_width: int = 0, arm_map: bool = False):
        super().__init__()
        self.arm_map = bool(arm_map)
        self.map_size = int(map_size or image_size // 2)  # action maps are drawn at this resolution
        if self.map_size % latent_size:
            raise ValueError(f"map_size {self.map_size} must be a multiple of latent_size {latent_size}")
        if sampling_steps < 1:
            raise ValueError(f"sampling_steps must be >= 1, got {sampling_steps}")
        if detail_gate < 0:
            raise ValueError(f"detail_gate must be >= 0 (0 = off), got {detail_gate}")
        self.image_size, self.chunk, self.sampling_steps = image_size, chunk, sampling_steps
        self.detail_gate = float(detail_gate)
        if not 0.0 <= noise_scale <= 1.0:
            raise ValueError(f"noise_scale must be in [0, 1], got {noise_scale}")
        self.noise_scale = float(noise_scale)
        if static_snap < 0:
            raise ValueError(f"static_snap must be >= 0 (0 = off), got {static_snap}")
        self.static_snap = float(static_snap)
        self.memory_offsets = tuple(int(o) for o in memory_offsets)
        if self.memory_offsets[0] != 0 or any(o < 0 for o in self.memory_offsets):
            raise ValueError(f"memory_offsets must start with 0 (the current frame), got {memory_offsets}")
        self.autoencoder = Autoencoder(image_size, latent_size, latent_channels, ae_widths, ae_patch)
        self.velocity = VelocityNet(latent_channels, len(self.memory_offsets), self.map_size, latent_size, chunk,
                                    width, map_channels, action_dim, use_raw_actions)
        if refiner_width < 0:
            raise ValueError(f"refiner_width must be >= 0 (0 = no refiner), got {refiner_width}")
        self.refiner = ArmRefiner(image_size, self.map_size, refiner_width) if refiner_width else None
        # latents are rescaled to unit variance and deltas to unit variance (set from data)
        self.register_buffer("latent_scale", torch.ones(()))
        self.register_buffer("delta_scale", torch.ones(()))

    @property
    def history(self) -> int:
        """How many past frames the memory reaches back."""
        return max(self.memory_offsets)

    @property
    def read_rows(self) -> tuple[int, ...]:
        """The chunk positions that a later chunk's memory reads when rollouts advance a whole chunk at a time
        (each memory is taken at a chunk's last frame, `o` steps back lands on position K-1 - o mod K): with
        offsets (0, 4, 8, 16) and K = 8, positions 3 and 7. Imagination that decodes only each chunk's last frame
        needs no other, so it predicts these alone (`rows` of `next_chunk`)."""
        return tuple(sorted({self.chunk - 1 - o % self.chunk for o in self.memory_offsets}))

    # -- latents -------------------------------------------------------------------------------
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """(..., 3, H, W) uint8 -> scaled latents (..., C, h, w)."""
        lead = images.shape[:-3]
        z = self.autoencoder.encode(images.reshape(-1, *images.shape[-3:])) / self.latent_scale
        return z.reshape(*lead, *z.shape[1:])

    def decode(self, z: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        """(..., C, h, w) scaled latents -> (..., 3, H, W) images in [0, 1]; with their action maps
        (..., 3, S, S) a model with a refiner redraws the robot where the maps put it."""
        lead = z.shape[:-3]
        x = self.autoencoder.decode(z.reshape(-1, *z.shape[-3:]) * self.latent_scale)
        if self.refiner is not None and maps is not None:
            x = self.refiner(x, maps.reshape(-1, *maps.shape[-3:]).to(x.dtype))
        return x.reshape(*lead, *x.shape[1:])

    def _condition(self, memory: torch.Tensor, action_maps: torch.Tensor, actions: torch.Tensor | None,
                   rows: tuple[int, ...] | None = None):
        """memory (B, M, C, h, w), action_maps (B, K, 3, S, S) -> per-frame conditioning for B*K items
        (`rows`: the chunk positions the K maps stand for; default 0..K-1)."""
        b, k = action_maps.shape[:2]
        mem = memory.flatten(1, 2)[:, None].expand(-1, k, -1, -1, -1).flatten(0, 1)
        index = torch.as_tensor(rows if rows is not None else range(k), device=memory.device).repeat(b)
        act = actions.flatten(0, 1).float() if actions is not None else None
        return mem, action_maps.flatten(0, 1).float(), index, act

    # -- training ------------------------------------------------------------------------------
    def flow_loss(self, memory: torch.Tensor, action_maps: torch.Tensor, target: torch.Tensor,
                  actions: torch.Tensor | None = None, valid: torch.Tensor | None = None,
                  generator: torch.Generator | None = None) -> torch.Tensor:
        """Rectified-flow loss. memory (B, M, C, h, w) and target (B, K, C, h, w) are scaled
        latents; the flow carries noise to the (scaled) change from the current latent."""
        mem, maps, index, act = self._condition(memory, action_maps, actions)
        x1 = ((target - memory[:, :1]) / self.delta_scale).flatten(0, 1)
        x0 = random_rows(torch.randn, x1.shape, generator, device=x1.device)
        t = random_rows(torch.rand, (x1.shape[0],), generator, device=x1.device)
        x_t = (1 - t[:, None, None, None]) * x0 + t[:, None, None, None] * x1
        err = (self.velocity(x_t, t, mem, maps, index, act) - (x1 - x0)).pow(2).mean(dim=(1, 2, 3))
        if valid is not None:
            w = valid.flatten().float()
            return (err * w).sum() / w.sum().clamp(min=1)
        return err.mean()

    # -- inference -----------------------------------------------------------------------------
    @torch.no_grad()
    def predict_latents(self, memory: torch.Tensor, action_maps: torch.Tensor, actions: torch.Tensor | None = None,
                        steps: int | None = None, generator: torch.Generator | None = None,
                        noise_scale: float | None = None, rows: tuple[int, ...] | None = None) -> torch.Tensor:
        """memory (B, M, C, h, w) scaled latents, action_maps (B, K, 3, S, S) in [0, 1] (S = map_size) ->
        next K latents (B, K, C, h, w), by `steps` Euler steps of the flow from noise of scale
        `noise_scale` (defaults: the config's). `rows`: only these chunk positions, the maps (and actions)
        given for them alone -> (B, len(rows), C, h, w), what the whole chunk's prediction holds there (each
        position is predicted from the same memory on its own, and draws the same noise)."""
        steps = int(steps or self.sampling_steps)
        if steps < 1:
            raise ValueError(f"sampling steps must be >= 1, got {steps}")
        noise_scale = self.noise_scale if noise_scale is None else float(noise_scale)
        b, k = action_maps.shape[:2]
        if rows is not None and (len(rows) != k or not all(0 <= r < self.chunk for r in rows)):
            raise ValueError(f"rows {tuple(rows)} must name the {k} chunk positions (of {self.chunk}) the maps are for")
        mem, maps, index, act = self._condition(memory, action_maps, actions, rows)
        # rows are rollout-major, so a list of generators (one per rollout group) splits them by group; a subset of
        # positions takes its rows of the whole chunk's draw, so it is the same sample
        x = random_rows(torch.randn, (b * (self.chunk if rows is not None else k), *memory.shape[2:]), generator,
                        device=memory.device) * noise_scale
        if rows is not None:
            x = x.view(b, self.chunk, *x.shape[1:])[:, list(rows)].flatten(0, 1)
        for i in range(steps):
            t = torch.full((b * k,), i / steps, device=x.device)
            x = x + self.velocity(x, t, mem, maps, index, act) / steps
        return memory[:, :1] + (x * self.delta_scale).view(b, k, *memory.shape[2:])

    def memory_indices(self, t: int) -> list[int]:
        """Frame indices (clamped at 0) that form the memory at step t."""
        return [max(0, t - o) for o in self.memory_offsets]

    def memory(self, latents: torch.Tensor) -> torch.Tensor:
        """(B, T, C, h, w) latent history, the last one current -> its memory (B, M, C, h, w)."""
        return latents[:, self.memory_indices(latents.shape[1] - 1)]

    @torch.no_grad()
    def next_chunk(self, latents: torch.Tensor, anchor: torch.Tensor, action_maps: torch.Tensor,
                   actions: torch.Tensor | None = None, steps: int | None = None,
                   generator: torch.Generator | None = None, noise_scale: float | None = None,
                   rows: tuple[int, ...] | None = None) -> torch.Tensor:
        """One open-loop chunk as imagination makes it: latents (B, T, C, h, w) the history so far
        (real, then imagined), anchor (B, C, h, w) the last real latent -> the next K latents, the
        flow's prediction from the history's memory with the static snap applied. Imagined rollouts
        and open-loop training both step through here, so training sees the errors inference makes."""
        z = self.predict_latents(self.memory(latents), action_maps, actions, steps=steps, generator=generator,
                                 noise_scale=noise_scale, rows=rows)
        return snap_static(z, anchor, self.static_snap) if self.static_snap > 0 else z


def snap_static(z: torch.Tensor, anchor: torch.Tensor, threshold: float) -> torch.Tensor:
    """z (B, K, C, h, w) predicted latents, anchor (B, C, h, w) the last real one: changes below
    `threshold` (mean |change| over channels) go back to the anchor, changes above 2x stay, a
    linear ramp between; the weight is max-pooled 3x3 so neighbours of a change keep theirs.
    (Why: worldenv_core/imagination/simulator.py, "Static snap".)"""
    change = z - anchor[:, None]
    size = change.abs().mean(dim=2, keepdim=True).flatten(0, 1)
    keep = F.max_pool2d((size / threshold - 1).clamp(0, 1), 3, stride=1, padding=1)
    return anchor[:, None] + change * keep.view(*z.shape[:2], 1, *z.shape[3:])
