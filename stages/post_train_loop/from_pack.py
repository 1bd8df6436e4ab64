"""LOOP in imagination from a context pack, on a machine with a GPU and neither the episodes, the
simulator nor the instruction encoder (a rented GPU). The same iteration (`rl_phase`), imagined
environment, Trainer and resumable checkpoints as `post_train_loop`, configured by its own config
(`key=value` overrides of `conf/post_train_loop.yaml`); no real evaluation (that is the stage's
and `evaluate`'s, back where the simulator is): the imagined reward and success on fixed contexts
and noise are measured before the first iteration, every `eval.every` iterations and at the end.
The result is a policy checkpoint folder that every stage takes (`policy_from=`), its meta saying
how it was trained.

    python -m stages.post_train_loop.context_pack '<episodes>' --out contexts.safetensors          # here
    python -m stages.post_train_loop.from_pack contexts.safetensors --policy <policy> \\
        --worldsim <world model> --reflector <reflector> --work w --minutes 8 [rl.n_rollouts=8 ...]  # there

`--minutes` sizes the run from a few timed iterations on copies of the policy (recorded in the
work dir, so a re-run resumes to the same total), and is also a deadline: the imagined evaluations
and longer later rollouts are not in the timing, so a run that would overrun saves its policy at the
first iteration past the deadline and stops (a re-run goes on to the total).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import logging
import time
from pathlib import Path

import torch

from stages.post_train_loop.context_pack import read_context_pack
from stages.post_train_loop.evaluation import imagined_success
from stages.post_train_loop.training import imagined_collector, rl_phase
from worldenv_core.contract import TaskContract
from worldenv_core.imagination.env import build_imagined_env
from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint, read_config
from worldenv_core.rl.loop import policy_param_groups
from worldenv_core.rl.termination import reflector_eta
from worldenv_core.stage import compose_config
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Trainer, pick_device, planned_steps, planned_total

log = logging.getLogger("worldenv.post_train_loop.from_pack")


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pack", help="a context pack (stages.post_train_loop.context_pack)")
    p.add_argument("--policy", required=True, help="the policy checkpoint folder to post-train")
    p.add_argument("--worldsim", required=True, help="the world model checkpoint folder")
    p.add_argument("--reflector", required=True, help="the reflector checkpoint folder")
    p.add_argument("--work", required=True, help="work dir: resumable checkpoints, curves, the result")
    how_long = p.add_mutually_exclusive_group(required=True)
    how_long.add_argument("--iterations", type=int)
    how_long.add_argument("--minutes", type=float, help="train for about this long: planned from timed steps, and saved and stopped at the "
                          "deadline if the plan runs over (a re-run goes on)")
    p.add_argument("overrides", nargs="*", help="post_train_loop settings, key=value (rl.*, eta, seed, eval.*)")
    args = p.parse_intermixed_args(argv)
    # --minutes is this sitting's wall clock, the plan's timing included: past it, the run saves and stops
    deadline = time.monotonic() + 60 * args.minutes if args.minutes else None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    contexts, keys, encoder, camera = read_context_pack(args.pack)
    task = read_config(args.policy)["meta"]["task"]
    cfg = compose_config("post_train_loop", [f"+task={task}", *args.overrides])
    # the task's contract as configured: the suite was checked against the benchmark's registry where
    # the pack was made (the benchmark need not be installed here)
    contract, rl = TaskContract.from_config(cfg.task), cfg.rl
    device = pick_device(cfg.device)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    encode = lambda s: encoder(s).to(device)  # noqa: E731

    policy, pmeta = load_checkpoint(args.policy, "policy", contract, device=str(device))
    eta = reflector_eta(args.reflector, cfg.eta)
    env, sim_camera = build_imagined_env(args.worldsim, args.reflector, eta, encode, rl.horizon, rl.sampling_steps,
                                         device, contract, rl.sampler_noise)
    if camera != sim_camera or policy.cameras != [camera]:
        raise CheckpointError(f"the pack's frames are from {camera!r}, the world model imagines {sim_camera!r}, "
                              f"the policy looks at {policy.cameras}: all three must be one camera")

    def phase(model, optimizer, iterations: int):
        with_iterations = copy.deepcopy(rl)
        with_iterations.iterations = iterations
        return rl_phase(model, optimizer, imagined_collector(env, contexts, rl.n_rollouts, encode), len(contexts),
                        with_iterations, cfg.seed)

    def time_iterations(seconds: float) -> int:  # on copies, so the run itself starts from the untouched policy
        probe_policy = copy.deepcopy(policy)
        probe_opt = torch.optim.Adam(policy_param_groups(probe_policy, rl.lr_backbone, rl.lr_heads))
        probe = phase(probe_policy, probe_opt, 4)
        return planned_steps(probe.step, iter(probe.batches(0)), seconds, probe=3, warm=1)

    iterations = planned_total(work, args.iterations, args.minutes, time_iterations, args.overrides)
    optimizer = torch.optim.Adam(policy_param_groups(policy, rl.lr_backbone, rl.lr_heads))
    pack_sha = hashlib.sha256(Path(args.pack).read_bytes()).hexdigest()[:12]
    meta = {**pmeta, "post_trained_from": args.policy, "worldsim": args.worldsim, "reflector": args.reflector,
            "trained_from": {"context_pack": pack_sha, "contexts": len(contexts), "iterations": iterations, "eta": eta,
                             "device": torch.cuda.get_device_name() if device.type == "cuda" else str(device)}}
    trainer = Trainer(work, policy, {"ppo": optimizer}, model_config=read_config(args.policy)["model"], meta=meta,
                      log_every=1, checkpoint_every=max(1, iterations // 20), desc="post_train_loop (pack)",
                      progress=cfg.progress, postfix=("mean_reward", "reflector_success_rate", "approx_kl"),
                      tracker=make_tracker(cfg.get("logger"), work, "post_train_loop", contract.name, {}))

    def evaluate(done: int, checkpoint: Path | None) -> dict:
        values = imagined_success(policy, env, contexts, cfg.eval.imagined_contexts, cfg.eval.imagined_rollouts, encode,
                                  cfg.seed) if cfg.eval.imagined_contexts else {}
        log.info("imagined evaluation at iteration %d: %s", done, json.dumps(values))
        return values

    log.info("LOOP from %s: %d contexts (%s ...), %d iterations of %d contexts x %d rollouts, eta %.2f, on %s",
             args.pack, len(contexts), keys[0], iterations, rl.contexts_per_iteration, rl.n_rollouts, eta, device)
    trainer.fit([phase(policy, optimizer, iterations)], evaluate=evaluate, evaluate_every=cfg.eval.every,
                deadline=deadline)
    final = trainer.save_final(work / "policy", iteration=trainer.step)
    trainer.close_off("training.png", f"post_train_loop from a context pack {contract.name}")
    log.info("saved %s (%d of %d iterations%s, %.0f s this sitting)", final, trainer.step, iterations,
             "; the deadline came first, a re-run goes on" if trainer.stopped_early else "", trainer.wall_s)
    return final


if __name__ == "__main__":
    main()
