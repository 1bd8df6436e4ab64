"""A sample of imagined rollouts kept as MCAP episodes, to look at in Foxglove beside real ones.

`record_imagined_rollouts` runs the policy in the imagined environment exactly as LOOP does
(same env, Laplace-sampled actions, reflector termination) with every frame decoded, and returns
one `Episode` per rollout (source "imagined") with the reflector's score at each chunk boundary;
`write_imagined_rollouts` writes them with the same schemas as real episodes plus a `/reflector`
channel (`worldenv_core.data.mcap_io.write_imagined_episode`). The Foxglove layout
`foxglove/imagined_vs_real.json` shows them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from worldenv_core.data.episode import JOINT_DIM, Episode, EpisodeMeta
from worldenv_core.data.mcap_io import write_imagined_episode
from worldenv_core.imagination.env import Context, ImaginedEnv, StepResult
from worldenv_core.rl.loop import collect_rollouts

# What an imagined episode cannot know; written as zeros / empty and said so in its metadata.
NOT_IMAGINED = "joint_pos zeros, sim_state empty: the world model imagines pixels and proprio only"


@dataclass
class ImaginedRollout:
    episode: Episode
    scores: dict[int, float]  # frame -> the reflector's R at that chunk boundary
    reward: float  # R at t_end, the reward LOOP would have used
    by_reflector: bool  # stopped because R > eta (an imagined success)


class ImaginedRecorder:
    """An observer for `collect_rollouts`: keeps every frame, proprio, action, mu and beta of each
    rollout, and the reflector's score at each chunk boundary, until the rollout ends."""

    def __init__(self):
        self.frames, self.proprio, self.actions, self.mu, self.beta = [], [], [], [], []
        self.scores: list[torch.Tensor] = []
        self.live: list[torch.Tensor] = []
        self.final: StepResult | None = None

    def on_reset(self, state: StepResult) -> None:
        self.frames.append(state.frames[:, None].cpu())
        self.proprio.append(state.proprio[:, None].float().cpu())
        self.scores.append(state.reward.float().cpu())
        self.final = state

    def on_step(self, actions: torch.Tensor, mu: torch.Tensor, beta: torch.Tensor, state: StepResult) -> None:
        if state.chunk_frames is None:
            raise RuntimeError("ImaginedRecorder needs every frame: set env.decode = 'all'")
        self.live.append(~self.final.done.cpu())  # the rollouts this chunk really advanced
        self.frames.append(state.chunk_frames.cpu())
        self.proprio.append(state.chunk_proprio.float().cpu())
        self.actions.append(actions.float().cpu())
        self.mu.append(mu.float().cpu())
        self.beta.append(beta.float().cpu())
        self.scores.append(state.reward.float().cpu())
        self.final = state

    def rollouts(self, contexts: list[Context], suite: str, task_names: dict[int, str], camera: str, chunk: int,
                 eta: float, fps: float, extra: dict[str, str]) -> list[ImaginedRollout]:
        frames = torch.cat(self.frames, 1)  # (B, 1 + C*K, 3, H, W)
        proprio = torch.cat(self.proprio, 1)
        actions, mu, beta = (torch.cat(x, 1) for x in (self.actions, self.mu, self.beta))  # (B, C*K, 7)
        out = []
        for i, ctx in enumerate(contexts):
            t_end = int(self.final.t[i])
            stopped = bool(self.final.by_reflector[i])
            success = np.zeros(t_end + 1, np.bool_)
            success[t_end:] = stopped  # the imagined verdict: done from the stop on
            n_chunks = sum(bool(live[i]) for live in self.live)
            scores = {0: float(self.scores[0][i])}
            scores |= {c * chunk: float(self.scores[c][i]) for c in range(1, n_chunks + 1)}
            meta = EpisodeMeta(suite=suite, task_id=ctx.task_id, task_name=task_names.get(ctx.task_id, ""),
                               instruction=ctx.instruction, init_state_index=-1, seed=0, source="imagined",
                               success=stopped, fps=fps, cameras=[camera],
                               extra={**extra, "eta": repr(float(eta)), "reward": repr(float(self.final.reward[i])),
                                      "not_imagined": NOT_IMAGINED})
            episode = Episode(
                meta=meta, images={camera: frames[i, : t_end + 1].permute(0, 2, 3, 1).numpy()},
                proprio=proprio[i, : t_end + 1].numpy(), joint_pos=np.zeros((t_end + 1, JOINT_DIM)),
                sim_state=np.zeros((t_end + 1, 0)), success=success, actions=actions[i, :t_end].numpy(),
                step_extras={"mu": mu[i, :t_end].numpy(), "beta": beta[i, :t_end].numpy()})
            out.append(ImaginedRollout(episode, scores, float(self.final.reward[i]), stopped))
        return out


@torch.no_grad()
def record_imagined_rollouts(policy, env: ImaginedEnv, contexts: list[Context], rollouts_per_context: int, encoder,
                             suite: str, task_names: dict[int, str], camera: str, extra: dict[str, str] | None = None,
                             generator: torch.Generator | None = None, fps: float = 20.0) -> list[ImaginedRollout]:
    """`rollouts_per_context` (>= 2, as LOOP draws them) imagined rollouts from each context, every
    frame decoded, as episodes with the reflector's scores."""
    recorder = ImaginedRecorder()
    decode, env.decode = env.decode, "all"
    try:
        collect_rollouts(policy, env, contexts, rollouts_per_context, encoder, generator=generator, observer=recorder)
    finally:
        env.decode = decode
    expanded = [c for c in contexts for _ in range(rollouts_per_context)]
    return recorder.rollouts(expanded, suite, task_names, camera, env.chunk, env.eta, fps, extra or {})


def imagined_replay(real: Episode, frames: torch.Tensor, proprio: torch.Tensor, extra: dict[str, str]) -> Episode:
    """The world model's open-loop replay of a recorded episode's actions from its first frame
    (`envs.imagined.replay_from_start(..., with_proprio=True)`), as an imagined episode: same
    actions, imagined frames (T+1, 3, H, W) uint8 and proprio (T+1, 7)."""
    camera = real.meta.cameras[0]
    n = real.num_frames
    meta = EpisodeMeta(suite=real.meta.suite, task_id=real.meta.task_id, task_name=real.meta.task_name,
                       instruction=real.meta.instruction, init_state_index=real.meta.init_state_index,
                       seed=real.meta.seed, source="imagined", success=False, fps=real.meta.fps, cameras=[camera],
                       extra={**extra, "replay_of_source": real.meta.source, "not_imagined": NOT_IMAGINED})
    return Episode(meta=meta, images={camera: frames[:n].permute(0, 2, 3, 1).numpy()},
                   proprio=proprio[:n].float().numpy(), joint_pos=np.zeros((n, JOINT_DIM)), sim_state=np.zeros((n, 0)),
                   success=np.zeros(n, np.bool_), actions=real.actions)


def write_imagined_rollouts(rollouts: list[ImaginedRollout], out_dir: str | Path, eta: float) -> list[Path]:
    """`<out_dir>/rollout_NN_taskTT_{success,failure}.mcap`, one per rollout (the imagined verdict)."""
    out_dir = Path(out_dir)
    paths = []
    for n, r in enumerate(rollouts):
        verdict = "success" if r.by_reflector else "failure"
        name = f"rollout_{n:02d}_task{r.episode.meta.task_id:02d}_{verdict}.mcap"
        paths.append(write_imagined_episode(out_dir / name, r.episode, r.scores, eta))
    return paths
