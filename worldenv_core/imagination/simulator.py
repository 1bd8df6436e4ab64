"""Imagined rollouts: the world simulator stepped chunk by chunk, batched over rollouts.

`ImaginedSimulator` keeps, per rollout, the latent history (for the sparse memory), the current
proprio state and the arm's last motion (for the kinematic model's momentum), and for a model
whose maps draw the whole arm (`arm_map`) its joint angles. `step(actions)` advances every
rollout by one action chunk: kinematics gives s_{t+1..t+K} (and the joints tracked onto them),
the camera draws their action maps, the world model predicts the K latents. Pixels are decoded
only on request.

Detail transfer (the model's `detail_gate` > 0): the autoencoder blurs what it reconstructs (its SSIM
ceiling is below copying the last frame), while the camera is fixed and most of the scene does
not move. So decoded frames get back the last real frame's fine detail (real minus its own
reconstruction) wherever the decoded content has not changed from that frame's reconstruction;
where it has (the arm, a moved object) the model's own pixels stand. The gate is soft:
weight 1 - min(1, change / detail_gate), change = the mean absolute change over colour
channels, max-pooled over a small window so edges of moving parts are not touched.

Static snap (the model's `static_snap` > 0): open loop, every chunk starts from the previous
imagined latent, so small errors where nothing moves compound over chunks and the background
slowly drifts and blurs (measured: the static region's SSIM falls from 0.98 to 0.86 over 64
steps while the moving region beats copy-last throughout). The camera is fixed, so a latent
position whose predicted change from the last real frame is small is snapped back to that
frame: weight on the change = clamp(change / static_snap - 1, 0, 1), dilated over the
neighbouring positions so the edges of moving parts keep their change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldenv_core.kinematics.action_map import arm_mask, draw_action_maps, draw_action_maps_per_rollout, gripper_mask
from worldenv_core.kinematics.arm import SerialArm, skeletons, track_rollouts
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import NextStateModel, observed_carry
from worldenv_core.models.worldsim import WorldSimulator


@dataclass
class ChunkResult:
    proprio: torch.Tensor  # (B, K, 7) s_{t+1..t+K}
    latents: torch.Tensor  # (B, K, C, h, w); only the positions `rows` where the chunk was not decoded whole
    action_maps: torch.Tensor  # (B, K, 3, H, W); likewise
    frames: torch.Tensor | None = None  # (B, K, 3, H, W) uint8 ("all") or (B, 1, 3, H, W) ("last")
    joints: torch.Tensor | None = None  # (B, K, 7) the arm's tracked joint angles (a model with `arm_map`)
    rows: tuple[int, ...] | None = None  # the chunk positions `latents` and `action_maps` hold (None: all K)


class ImaginedSimulator:
    def __init__(self, model: WorldSimulator, kinematics: NextStateModel, camera: PinholeCamera,
                 sampling_steps: int | None = None, device: str | torch.device = "cpu", detail_gate: float | None = None,
                 noise_scale: float | None = None, arm: SerialArm | None = None):
        if camera.image_size != model.image_size:
            raise ValueError(f"camera renders {camera.image_size} px but the world model makes {model.image_size} px")
        self.model = model.to(device).eval()
        self.kinematics, self.camera = kinematics, camera
        self.steps = sampling_steps
        if noise_scale is not None and not 0.0 <= noise_scale <= 1.0:
            raise ValueError(f"the sampler's noise_scale must be in [0, 1], got {noise_scale}")
        self.noise = noise_scale  # the flow sampler's temperature; None: the checkpoint's (0: the conditional mean)
        self.detail_gate = float(model.detail_gate if detail_gate is None else detail_gate)  # None: the checkpoint's
        if self.detail_gate < 0:
            raise ValueError(f"detail_gate must be >= 0 (0 = off), got {self.detail_gate}")
        self.anchor: tuple[torch.Tensor, torch.Tensor] | None = None  # (reconstruction, detail) of the last real frame
        self.anchor_latent: torch.Tensor | None = None  # (B, C, h, w) the last real frame's latent
        self.device = torch.device(device)
        # (B, T, C, h, w), all frames so far (NaN where a chunk was not decoded whole and no memory reads)
        self.latents: torch.Tensor | None = None
        self.proprio: torch.Tensor | None = None
        self.carry = None
        self.rollout_cameras: list[PinholeCamera] | None = None  # per rollout, when they differ
        self.arm = arm  # the arm of `camera`'s scene (a model with `arm_map` draws its links)
        self.rollout_arms: list[SerialArm] | None = None  # per rollout
        self.joints: torch.Tensor | None = None  # (B, 7) the arm's current joint angles

    @classmethod
    def from_checkpoint(cls, path, task_id: int, sampling_steps: int | None = None, device="cpu",
                        contract=None, noise_scale: float | None = None) -> "ImaginedSimulator":
        """A trained world simulator (a train_worldsim checkpoint folder) set up for one task:
        its kinematic model and that task's camera travel in the checkpoint's metadata."""
        from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint

        model, meta = load_checkpoint(path, "worldsim", contract)
        if str(task_id) not in meta["cameras"]:
            raise CheckpointError(f"world simulator {path} was trained on tasks {sorted(meta['cameras'])}, not task {task_id}")
        arms = checkpoint_arms(meta, model, path)
        return cls(model, NextStateModel(**meta["kinematics"]), PinholeCamera.from_dict(meta["cameras"][str(task_id)]),
                   sampling_steps=sampling_steps, device=device, noise_scale=noise_scale, arm=arms.get(task_id))

    @torch.no_grad()
    def reset(self, frames: torch.Tensor, proprio: torch.Tensor, prev_proprio: torch.Tensor | None = None,
              cameras: list[PinholeCamera] | None = None, joints: torch.Tensor | None = None,
              arms: list[SerialArm] | None = None) -> None:
        """frames (B, T0, 3, H, W) uint8: the real frames so far (T0 >= 1, the last is current);
        proprio (B, 7) the current state; prev_proprio (B, 7) the one before (momentum), if any;
        cameras: one per rollout when the batch mixes tasks of different scenes (default: `camera`);
        joints (B, 7): the arm's joint angles now (needed by a model with `arm_map`), arms: one per
        rollout, as cameras (default: `arm`)."""
        if frames.dim() != 5 or frames.shape[-1] != self.model.image_size:
            raise ValueError(f"frames must be (B, T, 3, {self.model.image_size}, {self.model.image_size}), got {tuple(frames.shape)}")
        if cameras is not None and any(c.image_size != self.model.image_size for c in cameras):
            raise ValueError(f"a rollout camera does not render {self.model.image_size} px")
        self.rollout_cameras = list(cameras) if cameras is not None else None
        self.joints, self.rollout_arms = None, None
        if self.model.arm_map:  # without joints it can only render (a step asks for them)
            self.rollout_arms = list(arms) if arms is not None else [self.arm] * len(frames)
            if len(self.rollout_arms) != len(frames) or any(a is None for a in self.rollout_arms):
                raise ValueError("this world model draws the arm's links: reset needs each rollout's arm")
            self.joints = None if joints is None else joints.to(self.device, torch.float64)
        self.latents = self.model.encode(frames.to(self.device))
        self.anchor_latent = self.latents[:, -1]
        self.proprio = proprio.to(self.device, torch.float64)
        if self.detail_gate > 0:  # the anchor is decoded as imagined frames are, its own map included
            now = None if self.joints is None else self.joints[:, None]
            recon = self.render_plain(self.latents[:, -1:], self._maps(self.proprio[:, None], now))[:, 0]
            self.anchor = (recon, frames[:, -1].to(self.device).float() / 255 - recon)
        self.carry = observed_carry(prev_proprio.to(self.device, torch.float64), self.proprio) if prev_proprio is not None else None

    def memory(self) -> torch.Tensor:
        return self.model.memory(self.latents)

    @torch.no_grad()
    def step(self, actions: torch.Tensor, decode: str = "all", generator: torch.Generator | None = None) -> ChunkResult:
        """actions (B, K, 7) in the simulator's units -> the next K imagined frames. `decode`:
        "all" frames to pixels, only the "last" (what a chunked policy looks at next), or "none"."""
        if decode not in ("all", "last", "none"):
            raise ValueError(f"decode must be 'all', 'last' or 'none', got {decode!r}")
        if self.latents is None:
            raise RuntimeError("call reset() before step()")
        b, k = actions.shape[:2]
        if b != self.latents.shape[0] or k != self.model.chunk:
            raise ValueError(f"actions must be ({self.latents.shape[0]}, {self.model.chunk}, 7), got {tuple(actions.shape)}")
        actions = actions.to(self.device)
        if self.model.arm_map and self.joints is None:
            raise ValueError("this world model draws the arm's links: reset needs the rollouts' joint angles "
                             "(a context's joint_pos) before a step")
        states, self.carry = self.kinematics.rollout(self.proprio, actions.double(), self.carry)
        joints = None
        if self.joints is not None:  # the links follow the imagined gripper
            joints = track_rollouts(self.rollout_arms, self.joints, states)
            self.joints = joints[:, -1]
        # Not decoded whole, a chunk is predicted only where later memories read it (`read_rows`: with the default
        # memory, positions 3 and 7 of 8): each position is predicted on its own from the same memory, so those are
        # what the whole chunk would hold, at a quarter of the flow network's and the maps' cost. The other
        # positions stay NaN in the history, which nothing reads.
        rows = None if decode == "all" else self.model.read_rows
        pick = slice(None) if rows is None else list(rows)
        maps = self._maps(states[:, pick], None if joints is None else joints[:, pick])
        z = self.model.next_chunk(self.latents, self.anchor_latent, maps, actions[:, pick].float(), steps=self.steps,
                                  generator=generator, noise_scale=self.noise, rows=rows)
        full = z
        if rows is not None:
            full = z.new_full((b, k, *z.shape[2:]), float("nan"))
            full[:, pick] = z
        self.latents = torch.cat([self.latents, full], dim=1)
        self.proprio = states[:, -1]
        kept = {"all": slice(None), "last": slice(-1, None), "none": None}[decode]
        frames = (self.render(z[:, kept], maps[:, kept]) * 255).round().to(torch.uint8) if kept is not None else None
        return ChunkResult(proprio=states.float(), latents=z, action_maps=maps, frames=frames,
                           joints=None if joints is None else joints.float(), rows=rows)

    @torch.no_grad()
    def overwrite_last(self, frames: torch.Tensor) -> None:
        """frames (B, 3, H, W) uint8: the newest frame as it should be read from now on (the robot layer's
        composite): its latent replaces the model's own, so the next chunk starts from it."""
        if self.latents is None or frames.shape[0] != self.latents.shape[0]:
            raise ValueError(f"overwrite_last needs one frame per rollout after a step, got {tuple(frames.shape)}")
        self.latents[:, -1] = self.model.encode(frames.to(self.device)[:, None])[:, 0]

    def _maps(self, states: torch.Tensor, joints: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n, 7) states (and (B, n, 7) joints, for a model that draws the arm) -> (B, n, 3, S, S)
        action maps, each rollout through its own camera."""
        points = skeletons(joints, self.rollout_arms).float() if joints is not None else None
        return (draw_action_maps(states.float(), self.camera, size=self.model.map_size, arm_points=points)
                if self.rollout_cameras is None
                else draw_action_maps_per_rollout(states, self.rollout_cameras, self.model.map_size, points))

    def render_plain(self, z: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n, C, h, w) latents -> (B, n, 3, H, W) in [0, 1], decoded (and, given the frames' action
        maps, refined where the model has a refiner), without detail transfer."""
        return self.model.decode(z, maps if self.model.refiner is not None else None)

    def render(self, z: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n, C, h, w) latents -> (B, n, 3, H, W) images in [0, 1], with detail transfer if on;
        `maps` (B, n, 3, S, S): the frames' action maps, for a model with a refiner."""
        x = self.render_plain(z, maps)
        if self.detail_gate <= 0:
            return x
        recon, detail = (a[:, None] for a in self.anchor)
        change = (x - recon).abs().mean(dim=2, keepdim=True).flatten(0, 1)
        # the 5x5 maximum as a 5x1 then a 1x5 one: the same numbers, about 0.7 of the time at 128 pixels
        change = torch.nn.functional.max_pool2d(change, (5, 1), stride=1, padding=(2, 0))
        change = torch.nn.functional.max_pool2d(change, (1, 5), stride=1, padding=(0, 2))
        change = change.view(*x.shape[:2], 1, *x.shape[3:])
        keep = (1 - change / self.detail_gate).clamp(min=0)
        return (x + keep * detail).clamp(0, 1)


def checkpoint_arms(meta: dict, model: WorldSimulator, path) -> dict[int, SerialArm]:
    """Each task's arm from a world model's metadata ({} for a model saved before arms were kept);
    a model that draws the arm must have them."""
    from worldenv_core.models.checkpoint import CheckpointError

    arms = {int(t): SerialArm.from_dict(a) for t, a in (meta.get("arms") or {}).items()}
    if model.arm_map and set(arms) != {int(t) for t in meta["cameras"]}:
        raise CheckpointError(f"world simulator {path} draws the arm's links but its metadata lacks the arms of tasks "
                              f"{sorted({int(t) for t in meta['cameras']} - set(arms))}")
    return arms


@torch.no_grad()
def open_loop_fidelity(sim: ImaginedSimulator, episodes, horizons=(8, 16, 32, 64), starts_per_episode: int = 2,
                       camera: str = "agentview", generator: torch.Generator | None = None) -> dict:
    """Replay held-out action sequences in imagination and compare with the real frames.

    From `starts_per_episode` start steps per episode (spread over it), the simulator gets the real
    frames so far and then only the recorded actions, open loop, for max(horizons) steps. Returns,
    per horizon h, PSNR and SSIM of the frame h steps ahead, for the model and for the
    copy-the-last-real-frame baseline, plus `videos`: (real, imagined) frame stacks of the first
    start of every episode for side-by-side viewing.

    SSIM is also split by region, to show where a model wins or loses: `moving` is where the real
    frame h steps ahead differs from the start frame (mean |difference| over colour > 0.04,
    dilated 7x7: the arm and what it moved), `static` the rest; `moving_fraction` its share; and
    `gripper`, the pixels around the real gripper's projection h steps ahead (`gripper_mask`: where
    the robot must stay sharp, whether or not it moved), with PSNR there too; and where the simulator
    knows its scene's arm (`arm`) and the episodes carry joint angles, `arm`: the whole robot's links
    at the real joints h steps ahead (`arm_mask`), with PSNR."""
    from worldenv_core.metrics import psnr, ssim_map

    k, longest = sim.model.chunk, max(horizons)
    n_chunks = -(-longest // k)
    keys = ("model_psnr", "model_ssim", "copy_psnr", "copy_ssim", "model_ssim_static", "copy_ssim_static",
            "model_ssim_moving", "copy_ssim_moving", "moving_fraction", "model_ssim_gripper", "copy_ssim_gripper",
            "model_psnr_gripper", "copy_psnr_gripper", "model_ssim_arm", "copy_ssim_arm", "model_psnr_arm", "copy_psnr_arm")
    rows = {h: {key: [] for key in keys} for h in horizons}
    videos = []
    for ep in episodes:
        imgs = ep.video(camera)
        proprio = torch.from_numpy(ep.proprio).double()
        actions = torch.from_numpy(ep.actions).float()
        last_start = ep.length - n_chunks * k
        if last_start < 1:
            continue
        starts = torch.linspace(1, last_start, starts_per_episode).round().long().unique().tolist()
        frames = replay_from_steps(sim, imgs, proprio, actions, starts, n_chunks, generator,
                                   torch.from_numpy(ep.joint_pos))
        for h in horizons:
            real = torch.stack([imgs[s + h] for s in starts]).float() / 255
            fake = frames[:, h - 1].float() / 255
            copy = torch.stack([imgs[s] for s in starts]).float() / 255
            rows[h]["model_psnr"] += psnr(fake, real).tolist()
            rows[h]["copy_psnr"] += psnr(copy, real).tolist()
            gripper = (gripper_mask(proprio[torch.tensor(starts) + h], sim.camera, real.shape[-1])
                       if sim.camera is not None else None)
            arm = None
            if sim.arm is not None and np.abs(ep.joint_pos).sum() > 0:  # imagined episodes carry no joints
                arm = arm_mask(sim.arm.points(torch.from_numpy(ep.joint_pos[[s + h for s in starts]])), sim.camera,
                               real.shape[-1])
            _ssim_by_region(rows[h], ssim_map(fake, real), ssim_map(copy, real), real, copy, gripper, arm=arm)
            for name, region in (("gripper", gripper), ("arm", arm)):
                if region is not None:
                    rows[h][f"model_psnr_{name}"] += psnr(fake, real, region).tolist()
                    rows[h][f"copy_psnr_{name}"] += psnr(copy, real, region).tolist()
        s0 = starts[0]
        videos.append((imgs[s0 + 1:s0 + 1 + frames.shape[1]], frames[0, : ep.length - s0]))
    summary = {h: {key: (sum(v) / len(v) if v else float("nan")) for key, v in r.items()} | {"n": len(r["model_psnr"])}
               for h, r in rows.items()}
    return {"horizons": summary, "videos": videos}


def _ssim_by_region(row: dict, model_map: torch.Tensor, copy_map: torch.Tensor, real: torch.Tensor,
                    start: torch.Tensor, gripper: torch.Tensor | None = None, threshold: float = 0.04,
                    arm: torch.Tensor | None = None) -> None:
    """Append whole-image and per-region SSIM of a batch (maps (N, H', W'), frames (N, 3, H, W);
    `gripper`, `arm` (N, H, W) bool: the gripper's and the whole arm's regions)."""
    change = (real - start).abs().mean(dim=1, keepdim=True)
    moving = torch.nn.functional.max_pool2d(change, 7, stride=1, padding=3)[:, 0] > threshold
    crop = (moving.shape[-1] - model_map.shape[-1]) // 2  # the SSIM map is `valid`: crop to it
    moving = moving[:, crop:moving.shape[-2] - crop, crop:moving.shape[-1] - crop]

    def cropped(mask):
        return mask[:, crop:mask.shape[-2] - crop, crop:mask.shape[-1] - crop] if mask is not None else [None] * len(moving)

    row["model_ssim"] += model_map.flatten(1).mean(1).tolist()
    row["copy_ssim"] += copy_map.flatten(1).mean(1).tolist()
    for mm, cm, mv, gr, am in zip(model_map, copy_map, moving, cropped(gripper), cropped(arm)):
        row["moving_fraction"].append(mv.float().mean().item())
        for name, region in (("static", ~mv), ("moving", mv), ("gripper", gr), ("arm", am)):
            if region is None:
                continue
            if region.any():
                row[f"model_ssim_{name}"].append(mm[region].mean().item())
                row[f"copy_ssim_{name}"].append(cm[region].mean().item())


@torch.no_grad()
def replay_from_start(sim: ImaginedSimulator, episodes, camera: str = "agentview",
                      generator: torch.Generator | None = None, with_proprio: bool = False) -> list:
    """Imagine each episode from its first real frame, driven by its recorded actions alone
    (open loop, batched over the episodes). Returns per episode (T+1, 3, H, W) uint8: the real
    first frame, then T imagined frames; `with_proprio`: (frames, (T+1, 7) imagined proprio)."""
    k = sim.model.chunk
    n_chunks = max(-(-ep.length // k) for ep in episodes)
    acts = torch.zeros(len(episodes), n_chunks * k, 7)
    for i, ep in enumerate(episodes):
        a = torch.from_numpy(ep.actions).float()
        acts[i, : len(a)] = a
        acts[i, len(a):] = a[-1]  # a finished episode holds its last command while the others go on
    first = torch.stack([torch.from_numpy(ep.images[camera][:1]).permute(0, 3, 1, 2) for ep in episodes])
    sim.reset(first, torch.stack([torch.from_numpy(ep.proprio[0]) for ep in episodes]).double(),
              joints=torch.stack([torch.from_numpy(ep.joint_pos[0]) for ep in episodes]))
    start = sim.proprio.float().cpu()[:, None]
    outs = [sim.step(acts[:, c * k:(c + 1) * k], generator=generator) for c in range(n_chunks)]
    frames = torch.cat([first, *(o.frames for o in outs)], dim=1)
    if not with_proprio:
        return [frames[i, : ep.length + 1] for i, ep in enumerate(episodes)]
    proprio = torch.cat([start, *(o.proprio.cpu() for o in outs)], dim=1)
    return [(frames[i, : ep.length + 1], proprio[i, : ep.length + 1]) for i, ep in enumerate(episodes)]


@torch.no_grad()
def rendered_copy(sim: ImaginedSimulator, imgs: torch.Tensor, block: int = 64) -> torch.Tensor:
    """An episode's real frames as the world model draws them, with no dynamics: each encoded and
    decoded (static detail laid back from the first frame, as in imagination). (T+1, 3, H, W) uint8 in
    and out; the first frame, the context, stays as it is."""
    sim.reset(imgs[None, :1], torch.zeros(1, 7, dtype=torch.float64))
    out = [imgs[:1]]
    for s in range(1, len(imgs), block):
        out.append((sim.render(sim.model.encode(imgs[None, s:s + block].to(sim.device)))[0] * 255).round()
                   .to(torch.uint8).cpu())
    return torch.cat(out)


@torch.no_grad()
def replay_from_steps(sim: ImaginedSimulator, imgs: torch.Tensor, proprio: torch.Tensor, actions: torch.Tensor,
                      starts: list[int], n_chunks: int, generator: torch.Generator | None = None,
                      joints: torch.Tensor | None = None) -> torch.Tensor:
    """One episode imagined from several of its steps at once (one batch): from each start s >= 1 the
    real frames up to s (the model's history), the state at s and at s - 1, then `n_chunks` chunks of
    the recorded actions from s, open loop (past the episode's end its last command is held).
    imgs (T+1, 3, H, W) uint8, proprio (T+1, 7), actions (T, 7), joints (T+1, 7) (what a model that
    draws the arm starts from) -> (len(starts), n_chunks * K, 3, H, W) uint8."""
    if min(starts) < 1:
        raise ValueError(f"a start needs the state before it: starts must be >= 1, got {min(starts)}")
    k = sim.model.chunk
    acts = actions.float()
    acts = torch.cat([acts, acts[-1:].expand(n_chunks * k, -1)])
    batch = torch.stack([acts[s:s + n_chunks * k] for s in starts]).view(len(starts), n_chunks, k, -1)
    proprio = proprio.double()
    sim.reset(_histories(imgs, starts, sim.model.history), proprio[starts], proprio[[s - 1 for s in starts]],
              joints=None if joints is None else joints[starts])
    return torch.cat([sim.step(batch[:, c], generator=generator).frames for c in range(n_chunks)], dim=1)


def _histories(imgs: torch.Tensor, starts: list[int], history: int) -> torch.Tensor:
    """The last `history` + 1 real frames before each start (edge-padded at the episode start)."""
    idx = torch.stack([torch.arange(s - history, s + 1).clamp(min=0) for s in starts])
    return imgs[idx]
