"""How LOOP trains in imagination: the imagined environment (world simulator + reflector reward),
the contexts rollouts start from, and one RL iteration as the Trainer's step."""

from __future__ import annotations

import copy
import time
from pathlib import Path

import torch

from worldenv_core.contract import TaskContract
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.env import Context, ImaginedEnv
from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.models.checkpoint import load_checkpoint, read_config
from worldenv_core.rl.loop import collect_rollouts, ppo_update
from worldenv_core.training import Phase, per_step, step_seed


def contexts_from_episodes(paths: list[Path], camera: str) -> list[Context]:
    out = []
    for p in paths:
        ep = read_episode(p, cameras=[camera])
        out.append(Context(task_id=ep.meta.task_id, instruction=ep.meta.instruction,
                           frame=torch.from_numpy(ep.images[camera][0]).permute(2, 0, 1).contiguous(),
                           proprio=torch.from_numpy(ep.proprio[0])))
    return out


def build_env(cfg, contract: TaskContract, worldsim_path: str, reflector_path: str, eta: float, encoder,
              device) -> tuple[ImaginedEnv, str]:
    """The imagined environment: the world simulator, each task's camera, the reflector as reward."""
    meta = read_config(worldsim_path)["meta"]
    cameras = {int(t): PinholeCamera.from_dict(c) for t, c in meta["cameras"].items()}
    sim = ImaginedSimulator.from_checkpoint(worldsim_path, min(cameras), cfg.rl.sampling_steps, device, contract)
    reflector, rmeta = load_checkpoint(reflector_path, "reflector", contract, device=str(device))
    if rmeta["camera"] != meta["camera"]:
        raise ConfigError(f"the reflector watches {rmeta['camera']!r} but the world simulator imagines {meta['camera']!r}")
    return ImaginedEnv(sim, cameras, reflector, encoder, eta, cfg.rl.horizon), meta["camera"]


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
