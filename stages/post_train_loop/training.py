"""How LOOP trains in imagination: the imagined environment (world simulator + reflector reward),
the contexts rollouts start from, and one RL iteration as the Trainer's step."""

from __future__ import annotations

import copy
import time
from pathlib import Path

import torch

from worldenv_core.data.mcap_io import read_episode
from worldenv_core.imagination.env import Context
from worldenv_core.rl.loop import collect_rollouts, ppo_update
from worldenv_core.training import Phase, per_step, step_seed


def contexts_from_episodes(paths: list[Path], camera: str) -> list[Context]:
    """LOOP's contexts: the first frame, proprio and instruction of each collected episode."""
    return [Context.from_episode(read_episode(p, cameras=[camera]), camera) for p in paths]


def rl_phase(policy, optimizer, env, contexts: list[Context], rl, encode, seed: int) -> Phase:
    """One iteration = one step: N rollouts from each of a few contexts by the frozen behaviour
    policy (Algorithm 1 line 3), then `ppo_epochs` passes of PPO on their RLOO advantages. An
    iteration's contexts, rollouts and minibatches are drawn from its own seed."""
    def step(g: torch.Generator) -> dict:
        t0 = time.perf_counter()
        picks = torch.randint(len(contexts), (rl.contexts_per_iteration,), generator=g).tolist()
        behaviour = copy.deepcopy(policy).eval()
        batch = collect_rollouts(behaviour, env, [contexts[i] for i in picks], rl.n_rollouts, encode, generator=g)
        stats = ppo_update(policy, optimizer, batch, rl.ppo_epochs, rl.epsilon, rl.minibatch, generator=g)
        return {"mean_reward": float(batch.rewards.mean()), "reflector_success_rate": float(batch.by_reflector.float().mean()),
                "episode_length": float(batch.t_end.float().mean()), "mean_beta": batch.beta_mean, **stats,
                "seconds": time.perf_counter() - t0}
    return Phase("rl", rl.iterations, lambda start: per_step(lambda it: torch.Generator().manual_seed(step_seed(seed, it)),
                                                             start), step)
