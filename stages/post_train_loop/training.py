"""How LOOP trains: the contexts rollouts start from, the two environments a rollout can run in
(the imagined one: world simulator + reflector reward; the real simulator: the oracle as reward,
the reference), and one RL iteration as the Trainer's step."""

from __future__ import annotations

import copy
import itertools
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import torch

from worldenv_core import distributed
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.envs.replay import RealStart
from worldenv_core.imagination.env import Context, mid_episode_frames
from worldenv_core.models.checkpoint import save_model
from worldenv_core.rl.loop import (RolloutBatch, check_success_range, collect_rollouts, informative_groups, merge,
                                   permute_verdicts, ppo_update, select)
from worldenv_core.rl.real_rollouts import collect_real_rollouts
from worldenv_core.training import Phase, per_step, step_seed

# (frozen behaviour policy, context indices, one generator per context) -> their rollouts
Collect = Callable[[torch.nn.Module, list[int], list[torch.Generator]], RolloutBatch]


def episode_starts(paths: list[Path], cameras: list[str], mid_frames: int):
    """(episode, where it starts in the real simulator) for each start frame of each collected
    episode: its first frame (the paper), or with `rl.mid_episode_frames` = mid_frames > 0, that many
    frames spread over its part before the first success."""
    from worldenv_core.data.mcap_io import read_episode  # here: LOOP from a context pack runs without MCAP

    for p in paths:
        ep = read_episode(p, cameras=cameras)
        for f in mid_episode_frames(ep.success, ep.length, mid_frames) if mid_frames else [0]:
            yield ep, RealStart(task_id=ep.meta.task_id, episode=str(p), frame=f)


def contexts_from_episodes(paths: list[Path], camera: str, mid_frames: int = 0) -> tuple[list[Context], list[RealStart]]:
    """LOOP's contexts (frame, proprio and instruction at each start frame of each collected
    episode) and where each starts in the real simulator (the paired replays at evaluations)."""
    pairs = [(Context.from_episode(ep, camera, st.frame), st) for ep, st in episode_starts(paths, [camera], mid_frames)]
    return [c for c, _ in pairs], [st for _, st in pairs]


def real_starts(paths: list[Path], mid_frames: int = 0) -> tuple[list[RealStart], list[str]]:
    """The same contexts in the real simulator (`env=real`): each start (its episode's scene rebuilt
    from its seed, its actions replayed up to the start frame), and its instruction."""
    pairs = [(st, ep.meta.instruction) for ep, st in episode_starts(paths, [], mid_frames)]
    return [st for st, _ in pairs], [i for _, i in pairs]


def imagined_collector(env, contexts: list[Context], n_rollouts: int, encode, noise_scale: float = 1.0) -> Collect:
    """Rollouts in the imagined environment (the method), actions drawn at `rl.noise_scale`."""
    return lambda behaviour, picks, gens: collect_rollouts(behaviour, env, [contexts[i] for i in picks], n_rollouts,
                                                           encode, generator=gens, noise_scale=noise_scale)


def placements(contract) -> Callable[[int], tuple[RealStart, str]]:
    """Context number k -> a fresh placement of the suite's tasks trained on (`rl.contexts=placements`):
    consecutive numbers cycle through the tasks, so an iteration's contexts spread evenly over them,
    and each number is its own placement (`envs.placements`, never a benchmark init state)."""
    from worldenv_core.envs.replay import placement_starts
    from worldenv_core.envs.tasks import get_task

    tasks = contract_task_ids(contract)

    def start(k: int) -> tuple[RealStart, str]:
        st = placement_starts(contract.suite, tasks, 1, "train", first=k)[0]
        return st, get_task(contract.suite, st.task_id).instruction
    return start


def real_collector(contract, starts: list[RealStart] | Callable[[int], tuple[RealStart, str]], instructions: list[str],
                   n_rollouts: int, encode, horizon: int, model_config: dict, meta: dict, folder: Path, workers,
                   progress: bool, noise_scale: float = 1.0) -> Collect:
    """Rollouts in the real simulator (`env=real`, the reference): the behaviour policy is saved
    under `folder` for the worker processes, one folder per iteration (a worker that ran the
    previous iteration must not reuse its cached weights), the previous one removed. `starts`:
    the contexts' list, or (fresh placements) a function of the context number."""
    count = itertools.count()
    lookup = starts if callable(starts) else (lambda i: (starts[i], instructions[i]))

    def collect(behaviour, picks, gens):
        for old in folder.glob("behaviour_*"):
            shutil.rmtree(old, ignore_errors=True)
        path = save_model(folder / f"behaviour_{next(count)}", behaviour, model_config, meta)  # weights copied to CPU
        chosen = [lookup(i) for i in picks]
        return collect_real_rollouts(behaviour, path, contract, [st for st, _ in chosen], [i for _, i in chosen],
                                     n_rollouts, encode, horizon, gens, workers=workers, progress=progress,
                                     noise_scale=noise_scale)
    return collect


def rl_phase(policy, optimizer, collect: Collect, n_contexts: int | None, rl, seed: int) -> Phase:
    """One iteration = one step: N rollouts from each of a few contexts by the frozen behaviour
    policy (Algorithm 1 line 3), then `ppo_epochs` passes of PPO on their RLOO advantages, over
    the groups whose verdicts disagree (`rl.filter_groups`; none: no update this iteration).
    An iteration's contexts, rollouts and minibatches are drawn from its own seed, each context's
    rollouts from a generator of its own. In a torchrun launch every rank imagines its share of
    the contexts, the rollouts are gathered, and every rank makes the same PPO update on all of
    them (rollouts are the cost; the update is cheap and needs no gradient exchange).
    `n_contexts` None: contexts without end (fresh placements), each iteration a run of
    consecutive context numbers from a random 40-bit start (distinct across iterations but for
    odds of about iterations^2 x contexts / 2^41). The recipe's other settings
    (`rl.group_success`, `rl.max_kl`, `rl.reset_optimizer`) are read here."""
    success_range = check_success_range(rl.get("group_success"))

    def step(g: torch.Generator) -> dict:
        t0 = time.perf_counter()
        if n_contexts is None:
            base = int(torch.randint(2**40, (1,), generator=g))
            picks = list(range(base, base + rl.contexts_per_iteration))
        else:
            picks = torch.randint(n_contexts, (rl.contexts_per_iteration,), generator=g).tolist()
        streams = [torch.Generator().manual_seed(s) for s in torch.randint(2**62, (len(picks),), generator=g).tolist()]
        mine = distributed.shard(list(range(len(picks))), distributed.rank(), distributed.world_size())
        behaviour = copy.deepcopy(policy).eval()
        batch = merge(distributed.gather(collect(behaviour, [picks[i] for i in mine], [streams[i] for i in mine])))
        if rl.verdicts == "permuted":  # the control: the same successes on other rollouts
            batch = permute_verdicts(batch, rl.n_rollouts, g)
        keep = (informative_groups(batch, rl.n_rollouts, success_range) if rl.filter_groups
                else torch.ones_like(batch.by_reflector))
        if rl.get("reset_optimizer"):  # each iteration's PPO from a fresh Adam (no moments from older batches)
            optimizer.state.clear()
        t_update = time.perf_counter()
        stats = (ppo_update(policy, optimizer, select(batch, keep), rl.ppo_epochs, rl.epsilon, rl.minibatch, generator=g,
                            target_kl=rl.target_kl, max_kl=rl.get("max_kl"), kl_states=rl.get("kl_states", 512),
                            direction_groups=rl.n_rollouts if rl.get("direction_check") else None)
                 if keep.any() else {})
        stats["update_seconds"] = time.perf_counter() - t_update
        stats.update({f"rollout_{k}_seconds": v for k, v in batch.timing.items()})  # summed over the rollouts
        distributed.broadcast_model(policy)  # the replicas made the same update; float noise must not make them drift
        return {"mean_reward": float(batch.rewards.mean()), "reflector_success_rate": float(batch.by_reflector.float().mean()),
                "episode_length": float(batch.t_end.float().mean()), "mean_beta": batch.beta_mean,
                "kept_groups": float(keep.float().mean()), **stats, "seconds": time.perf_counter() - t0}
    return Phase("rl", rl.iterations, lambda start: per_step(lambda it: torch.Generator().manual_seed(step_seed(seed, it)),
                                                             start), step)
