"""The real route's weight-space update (`rl.policy_update=es`, `worldenv_core/rl/es.py`): the members'
rollouts, one ARS step per iteration as the Trainer's step, and a run seeded from a ledger kept in the
repository, so a campaign goes on from where it was on a machine whose `outputs/` is empty."""

from __future__ import annotations

import contextlib
import copy
import itertools
import json
import logging
import shutil
import time
from pathlib import Path

import torch
from omegaconf import DictConfig

from stages.post_train_loop.training import draw_contexts, focus_positions, placements
from worldenv_core.envs.tasks import contract_task_ids
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.models.checkpoint import read_config, save_model
from worldenv_core.rl import es
from worldenv_core.rl.real_rollouts import collect_member_outcomes, journal_outcomes, restore_outcomes
from worldenv_core.training import Phase, per_step, step_seed
from worldenv_core.training.checkpoints import Checkpoints

log = logging.getLogger("worldenv.post_train_loop")


def es_collector(cfg, contract, src, encode, policy_path: str, pmeta: dict, work: Path):
    """(base policy, context numbers, members) -> every member's outcome from every context. Real: the base
    saved once per iteration as the PPO route's collector saves its behaviour policy, the members rebuilt
    from it in the workers, every finished rollout in the journal (`rl.keep_rollouts`: kept after).
    Imagined: all members' rollouts together through the world model, the reflector's verdict as success."""
    rl = cfg.rl
    if cfg.env != "real":
        return lambda base, picks, members: es.imagined_member_outcomes(
            base, src.env, [src.contexts[i] for i in picks], members, encode, rl.es_parameters)
    starts = placements(contract) if rl.contexts == "placements" else src.starts
    lookup = starts if callable(starts) else (lambda i: (src.starts[i], src.instructions[i]))
    model_config, count = read_config(policy_path)["model"], itertools.count()
    keep = work / "kept_rollouts" if rl.get("keep_rollouts") else None

    def collect(base, picks, members):
        for old in work.glob("behaviour_*"):
            shutil.rmtree(old, ignore_errors=True)
        path = save_model(work / f"behaviour_{next(count)}", base, model_config, pmeta)
        chosen = [lookup(i) for i in picks]
        return collect_member_outcomes(path, contract, [st for st, _ in chosen], [i for _, i in chosen], members,
                                       encode, rl.horizon, rl.es_parameters, workers=cfg.eval.workers,
                                       progress=cfg.progress, journal=work / "rollout_journal", keep=keep)
    return collect


def es_phase(policy, collect, n_contexts: int | None, rl, seed: int, ledger: Path | None = None,
             guard=None, n_tasks: int = 1, context_tasks: list[int] | None = None) -> Phase:
    """`rl.policy_update=es`: one iteration = `rl.es_pairs` antithetic weight-space members (`worldenv_core.rl.es`),
    each acting with its mean actions from the same `rl.contexts_per_iteration` contexts, then one ARS step.
    Contexts and directions are the iteration's generator's draws, so a resumed iteration runs the same
    members from the same starts (and takes its journal's finished rollouts back). `ledger`: a folder that
    keeps each iteration's contexts, seeds and outcomes (`iter_NNNN.json`): with the starting policy, all
    that the run's weights follow from (`es.replay_ledger`). `guard` (`training.paired_guard`, the imagined
    route): a step after which the policy's imagined successes fail for real beyond `rl.guard_max_hack_rate`
    is undone, and the ledger says so. `rl.task_focus` (of the `n_tasks` trained on): each iteration's
    contexts from that many tasks, in turn (listed contexts, e.g. keyframes: `context_tasks` names each one's task
    position). `rl.es_min_mixed`: no step from an iteration in which fewer
    contexts than that told any two members apart by their return (a full-size step would follow one or two
    starts' luck)."""
    def step(item) -> dict:
        it, g = item
        t0 = time.perf_counter()
        focus = focus_positions(it, rl.get("task_focus"), n_tasks)
        picks = draw_contexts(g, n_contexts, rl.contexts_per_iteration, focus, context_tasks)
        seeds = torch.randint(2**62, (rl.es_pairs,), generator=g).tolist()
        members = es.antithetic_members(seeds, rl.es_sigma)
        out = collect(copy.deepcopy(policy).eval(), picks, members)
        score = out["reward"] if rl.get("es_return", "success") == "score" else None
        per_context = es.context_returns(out["success"], out["steps"], rl.es_discount, score)
        returns = per_context.mean(0)
        t_update = time.perf_counter()
        before = [p.detach().clone() for _, p in es.es_parameters(policy, rl.es_parameters)] if guard else None
        mixed = es.mixed_contexts(per_context, es.SCORE_APART if score is not None else 0.0)
        if mixed >= rl.get("es_min_mixed", 1):
            stats = es.ars_update(policy, seeds, returns, rl.es_step, rl.get("es_top"), rl.es_parameters)
        else:  # made from too few starts to be the reward's direction: the ledger says no step was taken
            stats = {**es.pair_stats(seeds, returns, rl.get("es_top"))[0], "es_step_rms": 0.0, "no_step": 1.0}
        stats.update({"es_mixed_contexts": float(mixed), "update_seconds": time.perf_counter() - t_update,
                      **({"focus_task": float(focus[0][0])} if focus and len(focus[0]) == 1 else {})})
        if guard is not None and stats["es_step_rms"] > 0:
            stats.update(guard(policy))
            if stats["guard_hack_rate"] > rl.guard_max_hack_rate:  # NaN (no imagined success) passes
                with torch.no_grad():
                    for (_, p), old in zip(es.es_parameters(policy, rl.es_parameters), before):
                        p.copy_(old)
                stats["rolled_back"] = 1.0
                log.info("ES step undone: the guard's hack rate %.2f is above %.2f", stats["guard_hack_rate"],
                         rl.guard_max_hack_rate)
        if ledger is not None:
            es.write_ledger_entry(ledger, it + 1, picks, seeds, out["success"], out["steps"], returns, rl,
                                  rolled_back=bool(stats.get("rolled_back")), no_step=bool(stats.get("no_step")),
                                  score=score, focus_task=focus[0][0] if focus and len(focus[0]) == 1 else None)
        stats.update({f"rollout_{k}_seconds": v for k, v in out["timing"].items()})
        success = out["success"].float()
        return {"mean_reward": float(success.mean()), "reflector_success_rate": float(success.mean()),
                "episode_length": float(out["steps"].float().mean()), "train_episodes": float(out["episodes"]),
                "rollout_errors": float(out["errors"]), **stats, "seconds": time.perf_counter() - t0}
    return Phase("rl", rl.iterations, lambda start: per_step(
        lambda it: (it, torch.Generator().manual_seed(step_seed(seed, it))), start), step)


def context_tasks(cfg: DictConfig, contract, src) -> list[int] | None:
    """`rl.task_focus` over listed contexts (collected episodes' starts or keyframes): each context's position in the
    task list, every task trained on checked to have one before any rollout. None: fresh placements, or no focus."""
    if cfg.rl.get("task_focus") is None or src.n_contexts is None:  # fresh placements: numbered by task already
        return None
    order = {t: i for i, t in enumerate(contract_task_ids(contract))}
    tasks = [order[c.task_id] for c in (src.starts if cfg.env == "real" else src.contexts)]
    present = set(tasks)
    missing = sorted(t for t, i in order.items() if i not in present)
    if missing:
        raise ConfigError(f"rl.task_focus takes each task's contexts in turn, but task(s) {missing} have no context "
                          "(collect episodes of every task trained on)")
    return tasks


LEDGER_MUST_MATCH = ("es_pairs", "contexts_per_iteration", *es.LEDGER_SETTINGS)
IN_PROGRESS = "in_progress.json"  # the finished rollouts of the iteration a sitting ended inside


def seed_from_ledger(work: Path, ledger_from: str | Path, policy, optimizers: dict, model_config: dict, meta: dict,
                     rl, start: str | None = None) -> int:
    """`rl.es_ledger_from=<folder>` on a work dir with no checkpoint: the starting policy moved by the folder's
    ledger (`iter_NNNN.json`, `es.replay_ledger`) is checkpointed at its last iteration, with the run's history
    as far as the folder's `history.json` holds it, so the same command continues the run from there (a
    campaign's ledger kept in the repository outlives a machine's `outputs/`). The ledger's settings must be
    this run's; a folder that does not exist yet (the campaign's first sitting) seeds nothing. The finished rollouts
    of the iteration that was under way (`in_progress.json`) go back into the journal, where only the same jobs
    under the same behaviour weights take them. `start`: the starting policy's `es.weights_digest`, checked against
    the one the folder names. -> the iteration it starts from (0: nothing seeded)."""
    folder = Path(ledger_from)
    if start is not None and folder.exists():
        try:
            es.check_start(folder, start)
        except ValueError as e:
            raise ConfigError(f"rl.es_ledger_from={ledger_from}: {e}") from None
    checkpoints = Checkpoints(work)
    if checkpoints.last is not None:
        return 0
    if not folder.exists():  # a campaign's first sitting: the command names where its ledger will be kept
        log.warning("rl.es_ledger_from=%s does not exist yet: the run starts from the starting policy", folder)
        return 0
    try:
        entries = es.read_ledger(folder)
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(f"rl.es_ledger_from={ledger_from}: {e}") from None
    if not entries and not (folder / IN_PROGRESS).exists():
        raise ConfigError(f"rl.es_ledger_from={ledger_from} holds no iter_NNNN.json")
    for e in entries:
        shape = (len(e["success"]), len(e["success"][0]) if e["success"] else 0)
        settings = {**{k: e.get(k, es.LEDGER_DEFAULTS.get(k)) for k in es.LEDGER_SETTINGS}, "es_pairs": len(e["seeds"]),
                    "contexts_per_iteration": shape[0]}
        wrong = [k for k in LEDGER_MUST_MATCH if settings[k] != rl.get(k, es.LEDGER_DEFAULTS.get(k))]
        if wrong:
            raise ConfigError(f"rl.es_ledger_from={ledger_from}: iteration {e['iteration']} was made with "
                              + ", ".join(f"rl.{k}={settings[k]}" for k in wrong) + ", not this run's")
    done = min(len(entries), int(rl.iterations))
    if done:
        es.replay_ledger(policy, entries, done)
        for e in entries[:done]:
            es.write_ledger_entry(work / "es_ledger", e["iteration"], e["contexts"], e["seeds"],
                                  torch.tensor(e["success"]), torch.tensor(e["steps"]), torch.tensor(e["returns"]), rl,
                                  e.get("rolled_back", False), e.get("no_step", False),
                                  torch.tensor(e["score"]) if "score" in e else None, e.get("focus_task"))
        history = json.loads((folder / "history.json").read_text()) if (folder / "history.json").exists() else []
        history = [h for h in history if h.get("step", 0) <= done]
        evaluated = sorted({int(h["step"]) for h in history if "validation_success" in h or "real_success" in h})
        checkpoints.save(done, policy, model_config, meta, optimizers, history, trainer={"evaluated": evaluated})
        log.info("seeded %s from the ledger %s: %d iterations replayed on the starting policy", work, folder, done)
    if done == len(entries) and (folder / IN_PROGRESS).exists():  # the next iteration's finished rollouts
        n = restore_outcomes(work / "rollout_journal", json.loads((folder / IN_PROGRESS).read_text()))
        log.info("%d finished rollouts of iteration %d taken back from %s", n, done + 1, folder / IN_PROGRESS)
    return done


def export_ledger(work: Path, to: Path, start: str | None = None) -> Path:
    """A run's ledger and history (its last checkpoint's) copied to `to`, what `seed_from_ledger` reads, with the
    outcomes of the iteration under way (`in_progress.json`): an iteration of the whole suite is 1,280 episodes,
    more than an hour of these cores, and a session's end would otherwise lose what it had finished."""
    to.mkdir(parents=True, exist_ok=True)
    if start is not None:
        es.record_start(to, start)
    for f in sorted((work / "es_ledger").glob("iter_*.json")):
        shutil.copy2(f, to / f.name)
    # a sitting stopped between an iteration's step and the next one's start still holds the finished iteration's
    # journal: its members' seeds are in the ledger now, so its rollouts are not the iteration under way
    finished = {int(s) for e in es.read_ledger(to) for s in e["seeds"]}
    records = [r for r in journal_outcomes(work / "rollout_journal") if int(r["key"][-2][0]) not in finished]
    if records:
        write_text_atomic(to / IN_PROGRESS, json.dumps(records, separators=(",", ":")))
    else:
        (to / IN_PROGRESS).unlink(missing_ok=True)  # the iteration it held is in the ledger now
    last = Checkpoints(work).last
    if last is not None:
        history = torch.load(last / "training_state.pt", weights_only=False)["history"]
        (to / "history.json").write_text(json.dumps(history, indent=0, default=float))
    return to


@contextlib.contextmanager
def campaign_ledger(work: Path, rl, start: str | None = None):
    """`rl.es_ledger_from=<folder>` names a campaign's ledger kept outside `outputs/` (in the repository): the run
    is seeded from it (`seed_from_ledger`) and keeps it current. Yields the Trainer's `after_save`: the ledger and
    history exported after every iteration's checkpoint, and once more when the sitting is interrupted, with the
    iteration under way's finished rollouts, so a session's end or a lost machine costs nothing that was
    finished. Yields None for a run without a campaign folder."""
    folder = rl.get("es_ledger_from") if rl.policy_update == "es" else None
    if not folder:
        yield None
        return

    def keep(done: int | None = None) -> None:
        export_ledger(work, Path(folder), start)
    try:
        yield keep
    except KeyboardInterrupt:
        keep()
        log.info("the campaign's ledger and the iteration under way's finished rollouts kept in %s", folder)
        raise
