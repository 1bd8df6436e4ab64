"""How LOOP trains: the contexts rollouts start from (collected episodes' starts, fresh placements,
or a context pack's), the two environments a rollout can run in (the imagined one: world simulator +
reflector reward; the real simulator: the oracle as reward, the reference), the collector an
iteration draws its rollouts with, and one RL iteration as the Trainer's step."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig

from stages.post_train_loop.evaluation import PairedCheck, imagined_success
from worldenv_core import distributed
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.contract import TaskContract
from worldenv_core.envs.replay import RealStart, unreplayable
from worldenv_core.envs.replay_checks import replay_checks_file
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.context_pack import ContextPack, write_context_pack
from worldenv_core.imagination.env import WHOLE_DEPTH, Context, build_imagined_env, context_depth, mid_episode_frames
from worldenv_core.models.checkpoint import read_config, save_model
from worldenv_core.rl.critic import ChunkValue
from worldenv_core.rl.filtered_bc import SuccessBuffer, bc_update
from worldenv_core.rl.loop import (RolloutBatch, check_success_range, collect_rollouts, informative_groups, kl_probe,
                                   merge, permute_verdicts, ppo_update, select)
from worldenv_core.rl.real_rollouts import collect_real_rollouts
from worldenv_core.rl.termination import reflector_eta
from worldenv_core.training import Phase, per_step, step_seed

log = logging.getLogger("worldenv.post_train_loop")

# (frozen behaviour policy, context indices, one generator per context) -> their rollouts
Collect = Callable[[torch.nn.Module, list[int], list[torch.Generator]], RolloutBatch]


def episode_starts(paths: list[Path], cameras: list[str], mid_frames: int, depth=WHOLE_DEPTH):
    """(episode, where it starts in the real simulator) for each start frame of each collected
    episode: its first frame (the paper), or with `rl.mid_episode_frames` = mid_frames > 0, that many
    frames spread over its part before the first success (the `rl.context_depth` fraction of it)."""
    from worldenv_core.data.mcap_io import read_episode  # here: LOOP from a context pack runs without MCAP

    for p in paths:
        ep = read_episode(p, cameras=cameras)
        for f in mid_episode_frames(ep.success, ep.length, mid_frames, depth) if mid_frames else [0]:
            yield ep, RealStart(task_id=ep.meta.task_id, episode=str(p), frame=f)


def contexts_from_episodes(paths: list[Path], camera: str, mid_frames: int = 0, depth=WHOLE_DEPTH,
                           history_every: int = 0) -> tuple[list[Context], list[RealStart]]:
    """LOOP's contexts (frame, proprio and instruction at each start frame of each collected
    episode, and with `history_every` = the chunk a mid-episode frame's recorded past for the reward
    model) and where each starts in the real simulator (the paired replays at evaluations)."""
    pairs = [(Context.from_episode(ep, camera, st.frame, history_every), st)
             for ep, st in episode_starts(paths, [camera], mid_frames, depth)]
    return [c for c, _ in pairs], [st for _, st in pairs]


def real_starts(paths: list[Path], mid_frames: int = 0, depth=WHOLE_DEPTH) -> tuple[list[RealStart], list[str]]:
    """The same contexts in the real simulator (`env=real`): each start (its episode's scene rebuilt
    from its seed, its actions replayed up to the start frame), and its instruction."""
    pairs = [(st, ep.meta.instruction) for ep, st in episode_starts(paths, [], mid_frames, depth)]
    return [st for st, _ in pairs], [i for _, i in pairs]


def imagined_collector(env, contexts: list[Context], n_rollouts: int, encode, noise_scale: float = 1.0,
                       exploration: str = "step") -> Collect:
    """Rollouts in the imagined environment (the method), actions drawn at `rl.noise_scale`, a draw
    per step or per chunk (`rl.exploration`)."""
    return lambda behaviour, picks, gens: collect_rollouts(behaviour, env, [contexts[i] for i in picks], n_rollouts,
                                                           encode, generator=gens, noise_scale=noise_scale,
                                                           exploration=exploration)


def placements(contract) -> Callable[[int], tuple[RealStart, str]]:
    """Context number k -> a fresh placement of the suite's tasks trained on (`rl.contexts=placements`):
    consecutive numbers cycle through the tasks, so an iteration's contexts spread evenly over them,
    and each number is its own placement (`envs.placements`, never a benchmark init state). With
    `rl.placement_pool` = P the numbers are 0..P-1, drawn as collected episodes' starts are: P fixed
    placements, each revisited, between the paper's 5 starts per task and a new start per group."""
    from worldenv_core.envs.replay import placement_starts
    from worldenv_core.envs.tasks import get_task

    tasks = contract_task_ids(contract)

    def start(k: int) -> tuple[RealStart, str]:
        st = placement_starts(contract.suite, tasks, 1, "train", first=k)[0]
        return st, get_task(contract.suite, st.task_id).instruction
    return start


def real_collector(contract, starts: list[RealStart] | Callable[[int], tuple[RealStart, str]], instructions: list[str],
                   n_rollouts: int, encode, horizon: int, model_config: dict, meta: dict, folder: Path, workers,
                   progress: bool, noise_scale: float = 1.0, keep: Path | None = None, exploration: str = "step") -> Collect:
    """Rollouts in the real simulator (`env=real`, the reference): the behaviour policy is saved
    under `folder` for the worker processes, one folder per iteration (a worker that ran the
    previous iteration must not reuse its cached weights), the previous one removed. `starts`:
    the contexts' list, or (fresh placements) a function of the context number. Every finished
    rollout is kept in `folder/rollout_journal` until the next iteration's start, so an interrupted
    iteration resumes with the real episodes it had run; with `keep` (`rl.keep_rollouts`) each
    finished iteration's journal is moved there with its behaviour policy instead of removed."""
    count = itertools.count()
    lookup = starts if callable(starts) else (lambda i: (starts[i], instructions[i]))

    def collect(behaviour, picks, gens):
        for old in folder.glob("behaviour_*"):
            shutil.rmtree(old, ignore_errors=True)
        path = save_model(folder / f"behaviour_{next(count)}", behaviour, model_config, meta)  # weights copied to CPU
        chosen = [lookup(i) for i in picks]
        return collect_real_rollouts(behaviour, path, contract, [st for st, _ in chosen], [i for _, i in chosen],
                                     n_rollouts, encode, horizon, gens, workers=workers, progress=progress,
                                     noise_scale=noise_scale, journal=folder / "rollout_journal", keep=keep,
                                     exploration=exploration)
    return collect


def paired_guard(cfg: DictConfig, contract: TaskContract, src: "Rollouts", encode) -> Callable | None:
    """`rl.guard_contexts` > 0: policy -> the guard's figures after an update: its imagined rollouts from
    the same fixed contexts and noise every iteration, replayed for real (`guard_episodes`, counted), and
    the share of its imagined successes that fail there (`guard_hack_rate`; NaN without one)."""
    rl = cfg.rl
    if not rl.guard_contexts:
        return None
    check = PairedCheck(contract, src.starts, rl.guard_contexts, cfg.eval.workers, False)

    def guard(policy) -> dict:
        m = imagined_success(policy, src.env, src.contexts, rl.guard_contexts, rl.guard_rollouts, encode,
                             cfg.seed + 31, check)
        return {"guard_hack_rate": m["paired_hack_rate"], "guard_episodes": m["paired_episodes"],
                "guard_imagined_success": m["paired_imagined_success"], "guard_real_success": m["paired_real_success"]}
    return guard


def rl_phase(policy, optimizer, collect: Collect, n_contexts: int | None, rl, seed: int,
             guard: Callable | None = None, buffer: SuccessBuffer | None = None,
             critic: ChunkValue | None = None) -> Phase:
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
    (`rl.group_success`, `rl.max_kl`, `rl.reset_optimizer`) are read here. `guard` (`paired_guard`):
    an update after which its hack rate exceeds `rl.guard_max_hack_rate` is undone, weights and
    optimiser state (`rolled_back`). `rl.policy_update=filtered_bc`: instead of PPO, the iteration's successful
    rollouts join `buffer` and the policy's mean is fitted to all of the buffer's chunks
    (`filtered_bc.bc_update`, `rl.bc_steps` steps of `rl.bc_minibatch`). `critic` (`rl.advantages=gae`):
    PPO on per-chunk advantages from a value learned on the earlier iterations' rollouts, then fitted
    to this iteration's (`critic.ChunkValue`)."""
    filtered_bc = rl.get("policy_update", "ppo") == "filtered_bc"
    if filtered_bc and buffer is None:
        raise ValueError("rl.policy_update=filtered_bc needs a SuccessBuffer")
    success_range = check_success_range(rl.get("group_success"))

    def step(g: torch.Generator) -> dict:
        t0 = time.perf_counter()
        picks = draw_contexts(g, n_contexts, rl.contexts_per_iteration)
        stream_seeds = torch.randint(2**62, (len(picks),), generator=g).tolist()
        streams = [torch.Generator().manual_seed(s) for s in stream_seeds]
        mine = distributed.shard(list(range(len(picks))), distributed.rank(), distributed.world_size())
        behaviour = copy.deepcopy(policy).eval()
        batch = merge(distributed.gather(collect(behaviour, [picks[i] for i in mine], [streams[i] for i in mine])))
        if rl.verdicts == "permuted":  # the control: the same successes on other rollouts
            batch = permute_verdicts(batch, rl.n_rollouts, g)
        critic_stats = {}
        if critic is not None:  # credit per chunk from what the critic learned before this batch; then it learns this one
            t_critic = time.perf_counter()
            advantages, critic_stats = critic.advantages(policy, batch, g)
            batch = dataclasses.replace(batch, advantages=advantages)
            critic_stats["critic_seconds"] = time.perf_counter() - t_critic
        keep = (informative_groups(batch, rl.n_rollouts, success_range) if rl.filter_groups
                else torch.ones_like(batch.by_reflector))
        if rl.get("reset_optimizer"):  # each iteration's PPO from a fresh Adam (no moments from older batches)
            optimizer.state.clear()
        t_update = time.perf_counter()
        undo = ([p.detach().clone() for p in policy.parameters()], copy.deepcopy(optimizer.state_dict())) if guard else None
        if filtered_bc:  # the iteration's successes join the buffer under what drew the iteration (a resume rewrites it)
            key = hashlib.sha1(repr((picks, stream_seeds)).encode()).hexdigest()[:16]
            added = buffer.add(key, batch)
            stats = bc_update(policy, optimizer, buffer, rl.bc_steps, rl.bc_minibatch, g, rl.bc_augment_shift)
            probe = kl_probe(batch, rl.get("kl_states", 512), g)  # how far the update moved, in PPO's units
            stats.update({"buffer_added": added, **(probe.summary(policy) if probe is not None else {})})
        else:
            stats = (ppo_update(policy, optimizer, select(batch, keep), rl.ppo_epochs, rl.epsilon, rl.minibatch,
                                generator=g, target_kl=rl.target_kl, max_kl=rl.get("max_kl"),
                                kl_states=rl.get("kl_states", 512),
                                direction_groups=rl.n_rollouts if rl.get("direction_check") else None)
                     if keep.any() else {})
        stats.update(critic_stats)
        stats["update_seconds"] = time.perf_counter() - t_update
        if guard is not None and (stats.get("ppo_steps") or stats.get("bc_steps")):
            stats.update(guard(policy))
            if stats["guard_hack_rate"] > rl.guard_max_hack_rate:  # NaN (no imagined success) passes
                with torch.no_grad():
                    for p, old in zip(policy.parameters(), undo[0]):
                        p.copy_(old)
                optimizer.load_state_dict(undo[1])
                if filtered_bc:  # the successes the policy just imitated include the hacks the guard caught
                    buffer.remove(key)
                stats["rolled_back"] = 1.0
                log.info("update undone: the guard's hack rate %.2f is above %.2f", stats["guard_hack_rate"],
                         rl.guard_max_hack_rate)
        stats.update({f"rollout_{k}_seconds": v for k, v in batch.timing.items()})  # summed over the rollouts
        distributed.broadcast_model(policy)  # the replicas made the same update; float noise must not make them drift
        return {"mean_reward": float(batch.rewards.mean()), "reflector_success_rate": float(batch.by_reflector.float().mean()),
                "episode_length": float(batch.t_end.float().mean()), "mean_beta": batch.beta_mean,
                "kept_groups": float(keep.float().mean()), **stats, "seconds": time.perf_counter() - t0}
    return Phase("rl", rl.iterations, lambda start: per_step(lambda it: torch.Generator().manual_seed(step_seed(seed, it)),
                                                             start), step)


@dataclass
class Rollouts:
    """Where LOOP's rollouts run and start. Imagined: `env` and `contexts` (and `starts`, where each
    context begins in the real simulator, for the paired replays); real: `starts` and their
    `instructions`, or fresh placements (`n_contexts` None)."""
    camera: str
    eta: float | None = None
    env: object | None = None
    contexts: list[Context] = field(default_factory=list)
    starts: list[RealStart] = field(default_factory=list)
    instructions: list[str] = field(default_factory=list)
    keys: list[str] = field(default_factory=list)
    n_contexts: int | None = None


def rollouts(cfg: DictConfig, stage, contract: TaskContract, policy, encode, episodes, worldsim: str | None,
             reflector: str | None, pack: ContextPack | None, device) -> Rollouts:
    """The environment and contexts of this run, the camera checked against the policy's before any rollout."""
    rl = cfg.rl
    if cfg.env == "real":  # the reference: no world model, no reflector; the oracle decides
        out = Rollouts(camera=contract.cameras[0])
        if rl.contexts == "placements":  # None: a new placement per context; P: the same P placements throughout
            out.n_contexts = rl.get("placement_pool") or None
        else:
            out.starts, out.instructions = real_starts(episodes, rl.mid_episode_frames, context_depth(rl))
            keep = chosen(cfg, stage, contract, out.starts)
            out.starts, out.instructions = [out.starts[i] for i in keep], [out.instructions[i] for i in keep]
            out.n_contexts = len(out.starts)
    else:
        eta = reflector_eta(reflector, cfg.eta)
        env, camera = build_imagined_env(worldsim, reflector, eta, encode, rl.horizon, rl.sampling_steps, device,
                                         contract, rl.sampler_noise)
        out = Rollouts(camera=camera, eta=eta, env=env)
        if pack is not None:  # chosen where the episodes are, by the same rules
            out.contexts, out.keys = pack.contexts, pack.keys
        else:
            contexts, starts = contexts_from_episodes(episodes, camera, rl.mid_episode_frames, context_depth(rl),
                                                      contract.chunk)
            keep = chosen(cfg, stage, contract, starts)
            out.contexts, out.starts = [contexts[i] for i in keep], [starts[i] for i in keep]
            out.keys = [st.key for st in out.starts]
        out.n_contexts = len(out.contexts)
    if policy.cameras != [out.camera]:
        where = "env=real renders only" if cfg.env == "real" else "the world simulator imagines only"
        raise ConfigError(f"the policy looks at {policy.cameras}, but {where} {out.camera!r}")
    if out.n_contexts == 0:
        raise ConfigError(f"no collected episode of task(s) {sorted(contract_task_ids(contract))} to start rollouts from")
    return out


def chosen(cfg: DictConfig, stage, contract: TaskContract, starts: list[RealStart]) -> list[int]:
    """The starts of the tasks trained on (`task.task_ids`), less the mid-episode ones whose recorded
    prefix does not replay (no real rollout or paired replay could start there), dropped and named
    before any rollout."""
    task_ids = set(contract_task_ids(contract))
    mine = [i for i, st in enumerate(starts) if st.task_id in task_ids]
    errors = unreplayable(contract, [starts[i] for i in mine], cache=replay_checks_file(cfg), workers=cfg.eval.workers,
                          progress=cfg.progress) if cfg.rl.mid_episode_frames else {}
    for error in errors.values():
        log.warning("context dropped: %s", error)
    stage.metrics["dropped_contexts"] = len(errors)
    return [i for i in mine if starts[i].key not in errors]


def draw_contexts(g: torch.Generator, n_contexts: int | None, count: int,
                  focus: tuple[list[int], int] | None = None, context_tasks: list[int] | None = None) -> list[int]:
    """An iteration's context numbers, its generator's first draw: `count` of the `n_contexts` at
    random with replacement, or (None: fresh placements) consecutive numbers from a random 40-bit
    start. Iteration i (from 0) draws from `Generator().manual_seed(step_seed(seed, i))`, so which
    contexts any iteration of a run saw follows from its seed (`analysis.pool_revisits`). `focus`:
    (positions in the task list, its length): contexts of those tasks alone, in turn. Fresh placements:
    `placements` numbers placement k of the task at position k % length. Listed contexts (keyframes of
    collected episodes): `context_tasks` gives each one's task position, and each task's turn takes a
    context of its own at random, distinct ones while the task has any left this iteration."""
    if n_contexts is None:
        base = int(torch.randint(2**40, (1,), generator=g))
        if focus is None:
            return list(range(base, base + count))
        positions, n_tasks = focus
        return [n_tasks * (base + c // len(positions)) + positions[c % len(positions)] for c in range(count)]
    if focus is None:
        return torch.randint(n_contexts, (count,), generator=g).tolist()
    if context_tasks is None or len(context_tasks) != n_contexts:
        raise ValueError("a task focus over listed contexts needs each context's task position (context_tasks)")
    positions, _ = focus
    own = {p: [i for i, t in enumerate(context_tasks) if t == p] for p in positions}
    empty = [p for p, idx in own.items() if not idx]
    if empty:
        raise ValueError(f"no context of the task(s) at position(s) {empty} to focus on")
    queues = {p: [] for p in positions}
    out = []
    for c in range(count):
        p = positions[c % len(positions)]
        if not queues[p]:  # a fresh shuffle of the task's contexts: no repeat until every one was drawn
            queues[p] = [own[p][i] for i in torch.randperm(len(own[p]), generator=g).tolist()]
        out.append(queues[p].pop())
    return out


def focus_positions(iteration: int, per_iteration: int | None, n_tasks: int) -> tuple[list[int], int] | None:
    """`rl.task_focus` = m: iteration i (from 0) draws its contexts from m of the tasks trained on, the next
    m in turn (positions i*m .. i*m+m-1, modulo the task count), so a cycle of n/m iterations visits each
    task once; None (null): every task in every iteration."""
    if per_iteration is None:
        return None
    return [(iteration * per_iteration + j) % n_tasks for j in range(per_iteration)], n_tasks


def collector(cfg: DictConfig, contract: TaskContract, src: Rollouts, encode, policy_path: str, pmeta: dict, work):
    """How an iteration draws its rollouts: in imagination, or as real episodes (counted)."""
    rl = cfg.rl
    if cfg.env != "real":
        return imagined_collector(src.env, src.contexts, rl.n_rollouts, encode, rl.noise_scale, rl.exploration)
    starts = placements(contract) if rl.contexts == "placements" else src.starts
    return real_collector(contract, starts, src.instructions, rl.n_rollouts, encode, rl.horizon,
                          read_config(policy_path)["model"], pmeta, work, cfg.eval.workers, cfg.progress, rl.noise_scale,
                          keep=work / "kept_rollouts" if rl.get("keep_rollouts") else None, exploration=rl.exploration)


def pack_contexts(cfg: DictConfig, stage, contract: TaskContract, src: Rollouts, encoder) -> dict:
    """`contexts_to=`: the contexts this run would train from, with their instructions' embeddings,
    as a context pack; nothing is trained, and nothing recorded (no later stage may take the export
    for a post-trained policy)."""
    out = write_context_pack(cfg.contexts_to, src.contexts, src.keys, encoder, src.camera, contract.meta(),
                             {"mid_episode_frames": int(cfg.rl.mid_episode_frames), "expert_only": bool(cfg.expert_only),
                              "context_depth": list(context_depth(cfg.rl))})
    stage.not_recorded = f"it exported the contexts to {out}"
    stage.metrics.update({"context_pack": str(out), "contexts": len(src.contexts),
                          "pack_mib": round(out.stat().st_size / 2 ** 20, 1)})
    log.info("context pack %s: %d contexts, %.1f MiB", out, len(src.contexts), stage.metrics["pack_mib"])
    return stage.metrics


def check_pack(cfg: DictConfig, contract: TaskContract, pack: ContextPack, where: str) -> None:
    """A pack was chosen for this task and these settings: say which differs before any rollout."""
    contract.check(pack.task, where)
    if pack.task.get("task") != contract.name:
        raise ConfigError(f"{where} holds contexts of task {pack.task.get('task')!r}, this run is {contract.name!r}")
    frames = pack.settings.get("mid_episode_frames", 0)
    if frames != cfg.rl.mid_episode_frames:
        raise ConfigError(f"{where} was packed with rl.mid_episode_frames={frames}, this run has "
                          f"rl.mid_episode_frames={cfg.rl.mid_episode_frames}: pack again or set it")
    packed, mine = context_depth(pack.settings), context_depth(cfg.rl)
    if frames and packed != mine:
        raise ConfigError(f"{where} was packed with rl.context_depth={list(packed)}, this run has "
                          f"rl.context_depth={list(mine)}: pack again or set it")
