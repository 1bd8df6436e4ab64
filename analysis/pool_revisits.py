"""Does RL learn the starts it revisits? One iteration of a placement-pool run, read per start.

`rl.placement_pool=P` draws every iteration's contexts from the same P fresh placements (at random,
with replacement), so part of an iteration's batch are starts an earlier iteration trained on and
part are starts it has not seen. The same behaviour policy drew both, so the difference between
their success is what the earlier updates taught about those starts (task by task, since the tasks
differ in difficulty far more than any update moved them). Which contexts the earlier iterations drew
follows from the run's seed (`stages.post_train_loop.training.draw_contexts`); the judged iteration's
outcomes come from its rollout journal (`<work>/kept_rollouts/<digest>` once the next iteration began,
with `rl.keep_rollouts`; `<work>/rollout_journal/<digest>` while it runs).

    python -m analysis.pool_revisits +task=libero_spatial rl=explore rl.placement_pool=100 seed=0 \\
        --journal <work>/kept_rollouts/<digest> --iteration 4 --json results/rl_recipes/pool_revisits_iter4.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def seen_before(seed: int, iteration: int, pool: int, contexts: int, key_of) -> set[str]:
    """The start keys drawn by iterations 1 .. iteration - 1 of a run (iteration i draws with step i - 1's seed)."""
    import torch

    from stages.post_train_loop.training import draw_contexts
    from worldenv_core.training.batches import step_seed

    seen: set[str] = set()
    for it in range(iteration - 1):
        seen |= {key_of(k) for k in draw_contexts(torch.Generator().manual_seed(step_seed(seed, it)), pool, contexts)}
    return seen


def split(outcomes: dict[str, list[int]], seen: set[str]) -> dict:
    """Successes on seen against unseen starts: pooled, and task by task (keys 'taskT/...'); the
    task-balanced difference averages seen - unseen over the tasks that have both."""
    def rate(keys):
        s, n = sum(outcomes[k][0] for k in keys), sum(outcomes[k][1] for k in keys)
        return {"successes": s, "rollouts": n, "success": s / n if n else None, "starts": len(keys)}
    tasks = sorted({k.split("/")[0] for k in outcomes})
    per_task = {t: {"seen": rate([k for k in outcomes if k.startswith(t + "/") and k in seen]),
                    "unseen": rate([k for k in outcomes if k.startswith(t + "/") and k not in seen])} for t in tasks}
    both = [v["seen"]["success"] - v["unseen"]["success"] for v in per_task.values()
            if v["seen"]["rollouts"] and v["unseen"]["rollouts"]]
    return {"seen": rate([k for k in outcomes if k in seen]), "unseen": rate([k for k in outcomes if k not in seen]),
            "per_task": per_task, "tasks_with_both": len(both),
            "task_balanced_difference": sum(both) / len(both) if both else None}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--journal", type=Path, required=True, help="the judged iteration's rollout journal folder")
    ap.add_argument("--iteration", type=int, required=True, help="which iteration (from 1) drew that journal")
    ap.add_argument("--json", type=Path, help="write the split here")
    ap.add_argument("overrides", nargs="*", help="the run's Hydra overrides (+task=..., rl=..., rl.placement_pool=..., seed=...)")
    args = ap.parse_args(argv)
    with user_errors():
        from analysis.critic_probe import read_journal, start_outcomes
        from stages.post_train_loop.training import placements
        from worldenv_core.stage import compose_config, task_contract

        cfg = compose_config("post_train_loop", ["scale=small", *args.overrides])
        if not cfg.rl.get("placement_pool"):
            raise ConfigError("analysis.pool_revisits reads a placement-pool run: give its rl.placement_pool=P")
        if args.iteration < 2:
            raise ConfigError(f"--iteration {args.iteration}: the first iteration has no earlier one to have seen starts")
        start = placements(task_contract(cfg))
        seen = seen_before(int(cfg.seed), args.iteration, int(cfg.rl.placement_pool), int(cfg.rl.contexts_per_iteration),
                           lambda k: start(k)[0].key)
        out = {"journal": str(args.journal), "iteration": args.iteration,
               **split(start_outcomes(read_journal(args.journal, int(cfg.rl.n_rollouts))), seen)}
        for name in ("seen", "unseen"):
            r = out[name]
            print(f"{name}: {r['successes']}/{r['rollouts']} = {r['success']:.3f} over {r['starts']} starts")
        print(f"task-balanced seen - unseen: {out['task_balanced_difference']} over {out['tasks_with_both']} tasks")
        if args.json:
            write_text_atomic(args.json, json.dumps(out, indent=1))
        return out


if __name__ == "__main__":
    main()
