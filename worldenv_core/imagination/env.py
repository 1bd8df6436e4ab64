"""The imagined environment of LOOP (paper sec. 4.3, Algorithm 1 lines 8-19), vectorised.

`reset(contexts)` starts one rollout per context c = (instruction g, first frame o_1, proprio
s_1); `step(chunks)` takes an action chunk per rollout, advances the kinematics and the world
simulator (all rollouts in one batch on the model's device, whatever their tasks), scores each
prefix with the reflector (cached per-frame features) and marks a rollout done when R > eta or at
the horizon. The reward of a rollout is R at its termination step, t_end. A done rollout's
outputs are frozen: its later frames are neither scored nor returned as observations that count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worldenv_core.imagination.robot_layer import RobotLayer, Scene, composite
from worldenv_core.imagination.simulator import ImaginedSimulator, checkpoint_arms
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.rl.termination import check_eta


@dataclass
class Context:
    task_id: int
    instruction: str
    frame: torch.Tensor  # (3, H, W) uint8: o_1
    proprio: torch.Tensor  # (7,): s_1
    # (n, 3, H, W) uint8, oldest first: the recorded frames before o_1 a mid-episode context has (`history_steps`).
    # The reward model judges R(o_{1:t}, g) on the episode so far, as it was trained; shown only the frames from a
    # keyframe at 85 % on, the libero_spatial reflector recognised 6 of 10 held-out demos' successes 8 steps after
    # them, with the recorded prefix 9 (docs/notebook/verdict_fidelity.md). The world model never sees it.
    history: torch.Tensor | None = None
    joint_pos: torch.Tensor | None = None  # (7,): the arm's joint angles at o_1 (a world model that draws the arm needs them)
    scene: "Scene | None" = None  # the real scene at o_1 (a recorded episode's seed and MuJoCo state): the robot layer's

    @classmethod
    def from_episode(cls, ep, camera: str, t: int = 0, history_every: int = 0) -> "Context":
        """Frame `t` of a recorded episode (LOOP starts from t = 0); with `history_every` (the env's chunk, the
        spacing of the frames the reward model is shown) the recorded frames before it at that spacing."""
        images = ep.images[camera]
        sim_state = getattr(ep, "sim_state", None)  # an episode-like object may carry only what a context reads
        scene = (Scene(ep.meta.task_id, int(ep.meta.seed), sim_state[t].copy())
                 if sim_state is not None and sim_state.shape[1] else None)
        return cls(task_id=ep.meta.task_id, instruction=ep.meta.instruction, scene=scene,
                   frame=torch.from_numpy(images[t]).permute(2, 0, 1).contiguous(),
                   proprio=torch.from_numpy(ep.proprio[t]), history=history_frames(images, t, history_every),
                   joint_pos=None if getattr(ep, "joint_pos", None) is None else torch.from_numpy(ep.joint_pos[t]))


def history_frames(images: np.ndarray, t: int, every: int) -> torch.Tensor | None:
    """The recorded frames (T, H, W, 3) a context at frame t carries for the reward model, oldest first, as
    (n, 3, H, W): t - k * every for k >= 1 down to the episode's start (what a rollout from t = 0 would have
    shown it). None at an episode's start or with every = 0."""
    steps = list(range(t % every, t, every)) if every > 0 else []
    if not steps:
        return None
    return torch.from_numpy(np.stack([images[i] for i in steps])).permute(0, 3, 1, 2).contiguous()


WHOLE_DEPTH = (0.0, 1.0)  # rl.context_depth's default: the whole part of an episode before its success


def mid_episode_frames(success: np.ndarray, length: int, n: int,
                       depth: tuple[float, float] = WHOLE_DEPTH) -> list[int]:
    """n (>= 0) frames spread over the part of an episode before its first success (the task not yet
    done, so there is something left to judge), avoiding the first and the success frame. `depth`
    (lo, hi): only the fraction lo..hi of that part (e.g. (1/3, 1): where the imagined verdict is
    faithful, from about a third of the way into a task)."""
    lo, hi = check_depth(depth)
    hits = np.flatnonzero(success)
    end = int(hits[0]) if len(hits) else length
    return sorted({int(round(end * (lo + (hi - lo) * (i + 1) / (n + 1)))) for i in range(n)} - {0, end})


def context_depth(settings) -> tuple[float, float]:
    """`context_depth` of a run's rl settings or a context pack's, checked (before the setting: the whole part)."""
    return check_depth(settings.get("context_depth") or WHOLE_DEPTH)


def check_depth(depth) -> tuple[float, float]:
    """(lo, hi) with 0 <= lo < hi <= 1, or a ValueError naming what is wrong."""
    try:
        lo, hi = (float(x) for x in depth)
    except (TypeError, ValueError):
        raise ValueError(f"a context depth is two fractions [lo, hi] of an episode, got {depth!r}") from None
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"a context depth [lo, hi] needs 0 <= lo < hi <= 1, got [{lo}, {hi}]")
    return lo, hi


@dataclass
class StepResult:
    frames: torch.Tensor  # (B, 3, H, W) uint8: the newest frame of every rollout (what the policy sees next)
    proprio: torch.Tensor  # (B, 7)
    reward: torch.Tensor  # (B,) R(o_{1:t}, g) now; for done rollouts, R at t_end
    done: torch.Tensor  # (B,) bool
    t: torch.Tensor  # (B,) steps taken; for done rollouts, t_end
    by_reflector: torch.Tensor  # (B,) bool: stopped because R > eta (not by the horizon)
    # With `ImaginedEnv.decode = "all"` (recording rollouts to look at), every frame of the chunk:
    chunk_frames: torch.Tensor | None = None  # (B, K, 3, H, W) uint8
    chunk_proprio: torch.Tensor | None = None  # (B, K, 7)


class ImaginedEnv:
    def __init__(self, sim: ImaginedSimulator, cameras: dict[int, PinholeCamera], reflector, encoder, eta: float,
                 horizon: int, arms: dict | None = None, robot: RobotLayer | None = None):
        """sim: the world simulator + kinematics; cameras: task id -> the world model's camera in that
        task's scene; reflector: a reward model (the trained `Reflector`, or the VLM yes/no one)
        watching the same camera; encoder: instruction
        strings -> embeddings (the frozen MiniLM); arms: task id -> the arm of that scene (`SerialArm`), for a
        world model whose maps draw it; robot: the real renderer's robot over each chunk's last frame
        (`robot_layer.py`; every context then needs its `scene` and `joint_pos`)."""
        self.sim, self.cameras, self.reflector, self.encoder = sim, cameras, reflector.eval(), encoder
        self.robot = robot
        self.arms = arms or {}
        self.eta, self.horizon, self.chunk = check_eta(eta), int(horizon), sim.model.chunk
        self.scorer = None  # the reward model's incremental scorer of the current rollouts
        self.state: StepResult | None = None
        self.decode = "last"  # "all" also returns every frame of each chunk (costs a decode per frame)

    def reset(self, contexts: list[Context]) -> StepResult:
        missing = sorted({c.task_id for c in contexts} - set(self.cameras))
        if missing:
            raise ValueError(f"the world simulator has no camera for task(s) {missing}; it knows {sorted(self.cameras)}")
        device = self.sim.device
        frames = torch.stack([c.frame for c in contexts]).to(device)
        proprio = torch.stack([torch.as_tensor(c.proprio) for c in contexts]).double().to(device)
        joints = None
        if self.sim.model.arm_map:
            if any(c.joint_pos is None for c in contexts):
                raise ValueError("this world model draws the arm's links: every context needs its joint angles (joint_pos)")
            joints = torch.stack([torch.as_tensor(c.joint_pos, dtype=torch.float64) for c in contexts]).to(device)
        self.sim.reset(frames[:, None], proprio, cameras=[self.cameras[c.task_id] for c in contexts], joints=joints,
                       arms=[self.arms[c.task_id] for c in contexts] if self.sim.model.arm_map else None)
        if self.robot is not None:
            if any(c.scene is None or c.joint_pos is None for c in contexts):
                raise ValueError("the robot layer draws the arm in each context's real scene: every context needs its "
                                 "scene and joint angles (contexts from recorded episodes have them)")
            self.robot.reset([c.scene for c in contexts],
                             torch.stack([torch.as_tensor(c.joint_pos, dtype=torch.float64) for c in contexts]))
        self.scorer = self.reflector.scorer([c.instruction for c in contexts], self.encoder)
        if any(c.history is not None for c in contexts) and hasattr(self.scorer, "add_history"):
            self.scorer.add_history([None if c.history is None else c.history.to(device) for c in contexts])
        self.scorer.add(frames)
        b = len(contexts)
        self.state = StepResult(frames=frames, proprio=proprio.float(), reward=self.scorer.score(),
                                done=torch.zeros(b, dtype=torch.bool, device=device),
                                t=torch.zeros(b, dtype=torch.long, device=device),
                                by_reflector=torch.zeros(b, dtype=torch.bool, device=device))
        return self.state

    @torch.no_grad()
    def step(self, actions: torch.Tensor, generator: torch.Generator | None = None) -> StepResult:
        """actions (B, K, 7) in the simulator's units -> the state after the chunk."""
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        prev = self.state
        out = self.sim.step(actions, decode=self.decode, generator=generator)
        frames = out.frames[:, -1]
        if self.robot is not None:  # the arm redrawn where its joints are, and the next chunk starts from it
            frames = composite(frames, *self.robot.advance(out.proprio))
            self.sim.overwrite_last(frames)
            out.frames[:, -1] = frames
        self.scorer.add(frames)
        score = self.scorer.score()
        t = prev.t + self.chunk
        live = ~prev.done
        stop = live & (score > self.eta)
        timeout = live & ~stop & (t >= self.horizon)
        self.state = StepResult(
            frames=torch.where(live[:, None, None, None], frames, prev.frames),
            proprio=torch.where(live[:, None], out.proprio[:, -1], prev.proprio),
            reward=torch.where(live, score, prev.reward), done=prev.done | stop | timeout,
            t=torch.where(live, t, prev.t), by_reflector=prev.by_reflector | stop,
            chunk_frames=out.frames if self.decode == "all" else None,
            chunk_proprio=out.proprio if self.decode == "all" else None)
        return self.state


def check_horizon(horizon: int, label_delay: int, chunk: int) -> None:
    """An imagined horizon in which a success can be seen: the reflector calls a frame a success `label_delay` steps
    after the event and is asked every chunk, so a horizon under delay + chunk ends before any verdict (measured:
    16-step rollouts from late keyframes, 0 verdicts on real frames, docs/notebook/verdict_fidelity.md)."""
    from worldenv_core.errors import ConfigError

    if horizon < label_delay + chunk:
        raise ConfigError(f"an imagined horizon of {horizon} steps is shorter than the reflector's label delay "
                          f"({label_delay}) plus a chunk ({chunk}): no success could be seen in it; use at least "
                          f"{label_delay + chunk}")


def build_imagined_env(worldsim_path: str, reflector_path: str, eta: float, encoder, horizon: int,
                       sampling_steps: int | None, device, contract=None,
                       sampler_noise: float | None = None, robot_layer: bool = False) -> tuple[ImaginedEnv, str]:
    """The imagined environment LOOP trains in: the world simulator with each task's camera and
    the reflector as reward. Returns it and the camera it imagines. `sampling_steps` and
    `sampler_noise` override the world model's flow sampler (None: its own settings); `robot_layer`
    draws the robot with the real renderer over each chunk's last frame (needs the contract's suite)."""
    from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint, read_config

    meta = read_config(worldsim_path)["meta"]
    cameras = {int(t): PinholeCamera.from_dict(c) for t, c in meta["cameras"].items()}
    sim = ImaginedSimulator.from_checkpoint(worldsim_path, min(cameras), sampling_steps, device, contract, sampler_noise)
    arms = checkpoint_arms(meta, sim.model, worldsim_path)
    reflector, rmeta = load_checkpoint(reflector_path, "reflector", contract, device=str(device))
    if rmeta["camera"] != meta["camera"]:
        raise CheckpointError(f"the reflector watches {rmeta['camera']!r} but the world simulator imagines "
                              f"{meta['camera']!r}")
    check_horizon(horizon, int(rmeta.get("label_delay", 0)), sim.model.chunk)
    robot = None
    if robot_layer:
        if contract is None:
            raise ValueError("the robot layer renders the task's scenes: build_imagined_env needs the task contract")
        robot = RobotLayer(contract.suite, meta["camera"], sim.model.image_size)
    return ImaginedEnv(sim, cameras, reflector, encoder, eta, horizon, arms, robot), meta["camera"]
