"""What LOOP rolls out in and from: the imagined environment (world simulator + reflector) or the
real simulator (the reference), the contexts each starts from (collected episodes' starts, fresh
placements, or a context pack's), and the collector one RL iteration draws its rollouts with."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from omegaconf import DictConfig

from stages.post_train_loop.training import (contexts_from_episodes, imagined_collector, placements, real_collector,
                                             real_starts)
from worldenv_core.contract import TaskContract
from worldenv_core.envs.replay import RealStart, unreplayable
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.errors import ConfigError
from worldenv_core.imagination.context_pack import ContextPack, write_context_pack
from worldenv_core.imagination.env import Context, build_imagined_env
from worldenv_core.models.checkpoint import read_config
from worldenv_core.rl.termination import reflector_eta

log = logging.getLogger("worldenv.post_train_loop")


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
        if rl.contexts != "placements":
            out.starts, out.instructions = real_starts(episodes, rl.mid_episode_frames)
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
            contexts, starts = contexts_from_episodes(episodes, camera, rl.mid_episode_frames)
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
    errors = unreplayable(contract, [starts[i] for i in mine], workers=cfg.eval.workers,
                          progress=cfg.progress) if cfg.rl.mid_episode_frames else {}
    for error in errors.values():
        log.warning("context dropped: %s", error)
    stage.metrics["dropped_contexts"] = len(errors)
    return [i for i in mine if starts[i].key not in errors]


def collector(cfg: DictConfig, contract: TaskContract, src: Rollouts, encode, policy_path: str, pmeta: dict, work):
    """How an iteration draws its rollouts: in imagination, or as real episodes (counted)."""
    rl = cfg.rl
    if cfg.env != "real":
        return imagined_collector(src.env, src.contexts, rl.n_rollouts, encode, rl.noise_scale)
    starts = placements(contract) if src.n_contexts is None else src.starts
    return real_collector(contract, starts, src.instructions, rl.n_rollouts, encode, rl.horizon,
                          read_config(policy_path)["model"], pmeta, work, cfg.eval.workers, cfg.progress, rl.noise_scale)


def pack_contexts(cfg: DictConfig, stage, contract: TaskContract, src: Rollouts, encoder) -> dict:
    """`contexts_to=`: the contexts this run would train from, with their instructions' embeddings,
    as a context pack; nothing is trained, and nothing recorded (no later stage may take the export
    for a post-trained policy)."""
    out = write_context_pack(cfg.contexts_to, src.contexts, src.keys, encoder, src.camera, contract.meta(),
                             {"mid_episode_frames": int(cfg.rl.mid_episode_frames), "expert_only": bool(cfg.expert_only)})
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
