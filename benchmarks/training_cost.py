"""`make cost-model` (`python -m benchmarks.training_cost`): what each training stage costs per
step at a scale's model and batch sizes, measured on this machine, and the hours a whole run of
that scale needs at that rate (steps x median time per step) on one device.

Per (stage, scale) in a fresh process (so its peak memory is its own): the stage's models built
from the composed stage config (`+task=<task> scale=<scale>`, untrained: the cost does not depend
on the weights), synthetic batches of the configured shapes, the median over repeats of one
optimisation step (forward, backward, optimizer), and the process's peak resident memory.
post_train_loop: one iteration's imagined rollouts (C contexts x N rollouts, world model + reflector
+ policy per chunk) timed over 2 chunks and scaled to the horizon, plus its PPO epochs.
docs/scaling.md holds the table this prints (CPU); GPU figures are for a run on a GPU.
"""

from __future__ import annotations

import argparse
import copy
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

STAGES = ("train_policy", "train_worldsim", "train_reflector", "post_train_loop")


def _median_s(fn, repeats: int) -> float:
    fn()  # warm-up (allocations, kernel choice)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _camera(image_size: int):
    from worldenv_core.kinematics import PinholeCamera

    rot = np.array([[0.0, -0.63, 0.78], [1.0, 0.0, 0.0], [0.0, 0.78, 0.63]])  # looking down at the table
    return PinholeCamera("agentview", image_size, image_size * 1.2, np.array([0.66, 0.0, 1.61]), rot)


def _policy(cfg):
    from stages.train_policy.training import build_policy

    stats = {k: {"mean": np.zeros(7), "std": np.ones(7)} for k in ("proprio", "action")}
    return build_policy(cfg, stats, "cpu")


def policy_cost(cfg, repeats: int) -> dict:
    from stages.train_policy.training import action_step

    model, _, optimizers = _policy(cfg)
    b, size, chunk = cfg.train.batch_size, cfg.task.image_size, cfg.task.chunk
    batch = {"images": {c: torch.randint(0, 255, (b, 3, size, size), dtype=torch.uint8) for c in model.cameras},
             "proprio": torch.randn(b, 7), "instruction": [f"task {i % 10}" for i in range(b)],
             "actions": torch.randn(b, chunk, 7), "action_is_pad": torch.zeros(b, chunk, dtype=torch.bool)}
    step = action_step(model, optimizers["action"], lambda s: torch.randn(len(s), model.instruction_dim), "cpu",
                       cfg.train.augment_shift)
    s = _median_s(lambda: step(batch), repeats)
    return {"batch": b, "s_per_step": s, "steps": cfg.train.steps + cfg.scale_head.steps,
            "params_M": sum(p.numel() for p in model.parameters()) / 1e6}


def worldsim_cost(cfg, repeats: int) -> dict:
    from stages.train_worldsim.training import ae_phase, flow_phase

    model = instantiate(OmegaConf.to_container(cfg.worldsim, resolve=True), _convert_="all")
    ema = copy.deepcopy(model).requires_grad_(False)
    size, k, m = cfg.task.image_size, model.chunk, len(model.memory_offsets)
    opt_ae = torch.optim.AdamW(model.autoencoder.parameters(), lr=1e-3)
    opt_flow = torch.optim.AdamW(model.velocity.parameters(), lr=3e-4)
    ae = ae_phase(model, opt_ae, None, cfg, "cpu")
    flow = flow_phase(model, ema, opt_flow, None, {0: _camera(size)}, cfg, "cpu")
    frames = torch.randint(0, 255, (cfg.ae.batch_size, size, size, 3), dtype=torch.uint8)
    b, c, h = cfg.flow.batch_size, model.autoencoder.latent_channels, model.autoencoder.latent_size
    chunk = {"memory": torch.randn(b, m, c, h, h), "target": torch.randn(b, k, c, h, h),
             "proprio": torch.tensor([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 0.04]).repeat(b, k, 1),
             "actions": torch.randn(b, k, 7) * 0.3, "valid": torch.ones(b, k, dtype=torch.bool),
             "task_id": torch.zeros(b, dtype=torch.long)}
    s_ae, s_flow = _median_s(lambda: ae.step(frames), repeats), _median_s(lambda: flow.step(chunk), repeats)
    steps_ae, steps_flow = cfg.ae.steps, cfg.flow.steps
    return {"batch": f"{cfg.ae.batch_size} frames / {b} chunks", "s_per_step": (s_ae * steps_ae + s_flow * steps_flow)
            / (steps_ae + steps_flow), "steps": steps_ae + steps_flow, "s_ae": s_ae, "s_flow": s_flow,
            "params_M": sum(p.numel() for p in model.parameters()) / 1e6}


def _reflector(cfg):
    return instantiate(OmegaConf.to_container(cfg.reflector, resolve=True), _convert_="all")


def reflector_cost(cfg, repeats: int) -> dict:
    model = _reflector(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    b, f, size = cfg.train.batch_size, cfg.reflector.max_frames, cfg.task.image_size
    frames = torch.randint(0, 255, (b, f, 3, size, size), dtype=torch.uint8)
    mask, lang, label = torch.ones(b, f, dtype=torch.bool), torch.randn(b, 384), torch.rand(b).round()

    def step():
        from worldenv_core.training import optimize

        loss = torch.nn.functional.binary_cross_entropy_with_logits(model(frames, mask, lang), label)
        optimize(loss, opt, clip=1.0)
    return {"batch": b, "s_per_step": _median_s(step, repeats), "steps": cfg.train.steps,
            "params_M": sum(p.numel() for p in model.parameters()) / 1e6}


def loop_cost(cfg, repeats: int) -> dict:
    """One LOOP iteration: C x N imagined rollouts to the horizon, then PPO on them."""
    from worldenv_core.imagination.env import Context, ImaginedEnv
    from worldenv_core.imagination.simulator import ImaginedSimulator
    from worldenv_core.kinematics import NextStateModel
    from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update
    from worldenv_core.stage import compose_config

    rl, size, k = cfg.rl, cfg.task.image_size, cfg.task.chunk
    overrides = [f"+task={cfg.task.name}", f"scale={cfg.scale.name}"]
    policy, _, _ = _policy(compose_config("train_policy", overrides))
    worldsim = instantiate(OmegaConf.to_container(compose_config("train_worldsim", overrides).worldsim, resolve=True),
                           _convert_="all")
    reflector = _reflector(compose_config("train_reflector", overrides))
    cam = _camera(size)
    chunks = 2  # timed; the horizon's chunks scale it
    env = ImaginedEnv(ImaginedSimulator(worldsim, NextStateModel(), cam), {0: cam}, reflector,
                      lambda s: torch.randn(len(s), 384), eta=1.0, horizon=chunks * k)  # score > 1 never: no early stop
    contexts = [Context(task_id=0, instruction=f"task {i}", proprio=torch.tensor([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 0.04]),
                        frame=torch.randint(0, 255, (3, size, size), dtype=torch.uint8))
                for i in range(rl.contexts_per_iteration)]
    encode = lambda s: torch.randn(len(s), policy.instruction_dim)  # noqa: E731
    batch = {}

    def collect():
        batch["b"] = collect_rollouts(policy, env, contexts, rl.n_rollouts, encode, torch.Generator().manual_seed(0))
    s_collect = _median_s(collect, max(1, repeats // 2))
    opt = torch.optim.Adam(policy_param_groups(policy, rl.lr_backbone, rl.lr_heads))
    s_ppo = _median_s(lambda: ppo_update(policy, opt, batch["b"], rl.ppo_epochs, rl.epsilon, rl.minibatch), 1)
    per_horizon = -(-int(rl.horizon) // k) / chunks
    return {"batch": f"{rl.contexts_per_iteration} x {rl.n_rollouts} rollouts, {rl.horizon} steps",
            "s_per_step": (s_collect + s_ppo) * per_horizon, "steps": rl.iterations,
            "imagined_env_steps_per_s": rl.contexts_per_iteration * rl.n_rollouts * chunks * k / s_collect,
            "s_ppo_per_iteration": s_ppo * per_horizon}


COSTS = {"train_policy": policy_cost, "train_worldsim": worldsim_cost, "train_reflector": reflector_cost,
         "post_train_loop": loop_cost}


def _measure(stage: str, scale: str, task: str, repeats: int, threads: int) -> dict:
    from worldenv_core.stage import compose_config

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    out = COSTS[stage](compose_config(stage, [f"+task={task}", f"scale={scale}"]), repeats)
    out["peak_rss_GB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return out


def measure(stage: str, scale: str, task: str, repeats: int, threads: int) -> dict:
    """One (stage, scale) in a process of its own: its peak memory is its own."""
    cmd = [sys.executable, "-m", "benchmarks.training_cost", "--one", stage, scale, "--task", task,
           "--repeats", str(repeats), "--threads", str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode:
        raise RuntimeError(f"{stage} at scale {scale} failed:\n{out.stderr[-3000:]}")
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["hours"] = row["s_per_step"] * row["steps"] / 3600
    return row


def table(rows: list[dict]) -> str:
    lines = ["| stage | scale | batch | s / step | steps | hours on one device | peak memory (GB) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['stage']} | {r['scale']} | {r['batch']} | {r['s_per_step']:.3g} | {r['steps']} | "
                     f"{r['hours']:.3g} | {r['peak_rss_GB']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scales", nargs="+", default=["small", "paper"])
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    parser.add_argument("--task", default="libero_goal")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--json", default=None, help="also write the rows here")
    parser.add_argument("--one", nargs=2, metavar=("STAGE", "SCALE"), help=argparse.SUPPRESS)  # a child's measurement
    args = parser.parse_args()
    if args.one:
        print(json.dumps(_measure(*args.one, args.task, args.repeats, args.threads)))
        return
    rows = []
    for scale in args.scales:
        for stage in args.stages:
            row = measure(stage, scale, args.task, args.repeats, args.threads)
            rows.append({"stage": stage, "scale": scale, **row})
            print(json.dumps(rows[-1]), flush=True)
    print(table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"threads": args.threads, "device": "cpu", "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
