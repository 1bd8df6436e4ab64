"""`make bench` (`python -m benchmarks.bench`): what the real simulator and the world simulator
cost on this machine, side by side.

Prints medians over repeats (shared machines are noisy): env build, one physics-only step,
one camera render, the throughput of expert collection (kept frames per second), and imagined
env-steps per second of the world simulator at batch 8 against real env-steps per second
(physics + a render of the same camera at the same resolution every step), as a ratio.
The world model's cost does not depend on its weights, so an untrained model of the configured
architecture is timed unless `--worldsim <checkpoint>` names a trained one. Both sides get the
same CPU threads (`--threads`, default 1: torch threads, and the software renderer's threads).
`--only policy`: one chunk's forward (batch 1, as a rollout asks) of each policy config named by
`--policies` (default: the project's `small` and LeRobot's ACT, `lerobot_act`) at the task's image size,
untrained (the cost does not depend on the weights), with their parameter counts.
`--only robot_layer`: what the robot layer (`imagination.robot_layer`) adds to imagination, per rollout and
chunk (tracking the joints onto a chunk's end-effector states and drawing the robot at the last one), beside
a real chunk's physics and chunk-boundary render on the same thread.
`--only policy_episode`: a policy rollout as collection records it (`policy_episode`, then `to_episode`), the
recording timed with and without the chunk-boundary frames the policy was shown kept, alternating per episode: the
ratio is what keeping them saves (`--policy` a checkpoint; default an untrained `small` policy, the same cost).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np

from worldenv_core.envs.libero_env import LiberoEnv
from worldenv_core.envs.recording import attempt_seed, expert_attempt, to_episode


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def simulator_costs(suite: str, task_id: int, image_size: int, cameras: list[str], repeats: int) -> dict:
    t0 = time.perf_counter()
    env = LiberoEnv(suite, task_id, cameras=cameras, image_size=image_size)
    build_s = time.perf_counter() - t0
    env.reset(init_state=0)
    rng = np.random.default_rng(0)
    step_ms = statistics.median(
        _median_ms(lambda: env.step(np.r_[rng.uniform(-0.3, 0.3, 6), -1.0]), 20) for _ in range(repeats))
    render_ms = _median_ms(env.render, 10 * repeats)
    # Expert collection: physics-only attempts, then render the kept ones by replaying states.
    episodes = []
    for i in range(repeats):
        t0 = time.perf_counter()
        traj = expert_attempt(env, None, attempt_seed(0, suite, task_id, i, 0), env.max_steps)
        if traj.success:
            to_episode(env, traj, init_state_index=-1, seed=0, source="expert")
        episodes.append({"frames": traj.length + 1, "success": traj.success, "s": time.perf_counter() - t0})
    kept = [e for e in episodes if e["success"]]
    env.close()
    return {
        "suite": suite, "task_id": task_id, "image_size": image_size, "cameras": cameras,
        "env_build_s": round(build_s, 2),
        "physics_step_ms_median": round(step_ms, 2),
        "render_ms_per_frame_median": round(render_ms, 1),
        "expert_success": f"{len(kept)}/{len(episodes)}",
        "kept_frames_per_s_median": round(statistics.median(e["frames"] / e["s"] for e in kept), 2) if kept else None,
    }


def world_model_speed(suite: str, task_id: int, image_size: int, camera: str, repeats: int, batch: int,
                      checkpoint: str | None, sampling_steps=(1, 2, 4)) -> dict:
    """Imagined vs real env-steps per second, measured in this one process, for the same outputs:
    every frame rendered/decoded, or only the frame at each chunk boundary (what a chunked policy
    reads; the real simulator still steps its physics every step)."""
    import torch
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from worldenv_core.imagination.simulator import ImaginedSimulator
    from worldenv_core.kinematics import NextStateModel, PinholeCamera
    from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint
    from worldenv_core.stage import CONF_DIR

    chunk = 8
    if checkpoint:  # named before the simulator is built: a world model made for other frames times nothing real
        model, meta = load_checkpoint(checkpoint, "worldsim")
        if (meta.get("image_size"), meta.get("chunk")) != (image_size, chunk):
            raise CheckpointError(f"world model {checkpoint} was trained on {meta.get('image_size')}-pixel frames in "
                                  f"chunks of {meta.get('chunk')}, not {image_size} / {chunk} (--image-size)")
    else:
        cfg = OmegaConf.load(CONF_DIR / "worldsim" / "latent_flow.yaml")
        cfg.image_size, cfg.chunk, cfg.action_dim, cfg.latent_size = image_size, chunk, 7, 16
        model = instantiate(cfg, _convert_="all").eval()
    env = LiberoEnv(suite, task_id, cameras=[camera], image_size=image_size)
    first = env.reset(init_state=0)
    rng = np.random.default_rng(0)

    def real_step():
        env.step(np.r_[rng.uniform(-0.3, 0.3, 6), -1.0])
        env.render()

    t = [0]

    def real_chunk_step():  # physics every step, a render only where a chunked policy looks
        env.step(np.r_[rng.uniform(-0.3, 0.3, 6), -1.0])
        t[0] += 1
        if t[0] % chunk == 0:
            env.render()

    real_ms = statistics.median(_median_ms(real_step, 8) for _ in range(repeats))
    real_chunk_ms = statistics.median(_median_ms(real_chunk_step, 2 * chunk) for _ in range(repeats))
    cam = PinholeCamera.from_sim(env.sim, camera, image_size)
    frame0 = torch.from_numpy(env.render()[camera]).permute(2, 0, 1)
    env.close()
    torch.manual_seed(0)
    out = {"real_env_steps_per_s": {"every_frame": round(1000 / real_ms, 2),
                                    "chunk_boundary_frames": round(1000 / real_chunk_ms, 2)},
           "batch": batch, "chunk": chunk, "params_M": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
           "threads": torch.get_num_threads()}
    actions = torch.from_numpy(rng.uniform(-0.3, 0.3, (batch, chunk, 7))).float()
    for steps in sampling_steps:
        sim = ImaginedSimulator(model, NextStateModel(), cam, sampling_steps=steps)
        sim.reset(frame0[None, None].expand(batch, 1, -1, -1, -1), torch.from_numpy(first.proprio)[None].expand(batch, -1))
        for decode, real in (("all", real_ms), ("last", real_chunk_ms)):
            sim.step(actions, decode=decode)  # warm-up
            ms = statistics.median(_median_ms(lambda: sim.step(actions, decode=decode), 2) for _ in range(repeats))
            rate = batch * chunk * 1000 / ms
            key = "every_frame" if decode == "all" else "chunk_boundary_frames"
            out.setdefault(f"imagined_env_steps_per_s_{steps}step", {})[key] = round(rate, 1)
            out.setdefault(f"speedup_{steps}step", {})[key] = round(rate * real / 1000, 1)
    return out


def policy_costs(policies: list[str], suite: str, image_size: int, repeats: int) -> dict:
    """Milliseconds per chunk (median) and parameters of each policy config, inputs as a rollout gives them."""
    import torch
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from worldenv_core.stage import compose_config

    out = {}
    for name in policies:
        cfg = compose_config("train_policy", [f"+task={suite}", f"policy={name}", f"task.image_size={image_size}"])
        model = instantiate(OmegaConf.to_container(cfg.policy, resolve=True), _convert_="all").eval()
        images = {c: torch.randint(0, 256, (1, 3, image_size, image_size), dtype=torch.uint8) for c in model.cameras}
        proprio, lang = torch.zeros(1, 7), torch.zeros(1, 384)
        with torch.no_grad():
            model(images, proprio, lang)  # warm-up: first-call allocations
            ms = _median_ms(lambda: model(images, proprio, lang), repeats)
        out[name] = {"ms_per_chunk": round(ms, 1), "chunk": int(cfg.task.chunk),
                     "parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 2)}
    return out


def robot_layer_cost(suite: str, task_id: int, image_size: int, camera: str, repeats: int, batch: int) -> dict:
    """Milliseconds per rollout and chunk of the robot layer (median), against a real chunk of the same length."""
    import torch

    from worldenv_core.imagination.robot_layer import RobotLayer, Scene

    chunk = 8
    env = LiberoEnv(suite, task_id, cameras=[camera], image_size=image_size)
    frame = env.reset(seed=0)
    rng = np.random.default_rng(0)
    scene, joints = Scene(task_id, 0, frame.sim_state.copy()), torch.as_tensor(frame.joint_pos)
    states = []  # a real chunk's end-effector states: the layer tracks what the world model would imagine

    def real_chunk():
        for t in range(chunk):
            states.append(env.step(np.r_[rng.uniform(-0.3, 0.3, 6), -1.0]).proprio)
        env.render()  # what a chunked policy reads

    real_chunk()  # warm-up
    real_ms = statistics.median(_median_ms(real_chunk, 2) for _ in range(repeats))
    env.close()
    chunk_states = torch.as_tensor(np.stack(states[:chunk]))[None].expand(batch, -1, -1).contiguous()
    layer = RobotLayer(suite, camera, image_size)
    try:
        layer.reset([scene] * batch, joints[None].expand(batch, -1))
        layer.advance(chunk_states)  # builds its env and the seed's fixtures once, as the first chunk of a run

        def advance():
            layer.reset([scene] * batch, joints[None].expand(batch, -1))
            layer.advance(chunk_states)

        ms = statistics.median(_median_ms(advance, 2) for _ in range(repeats)) / batch
    finally:
        layer.close()
    return {"chunk": chunk, "batch": batch, "robot_layer_ms_per_rollout_chunk": round(ms, 1),
            "real_chunk_ms": round(real_ms, 1), "robot_layer_over_real_chunk": round(ms / real_ms, 2)}


def policy_episode_cost(suite: str, task_id: int, image_size: int, camera: str, repeats: int,
                        policy: str | None = None, steps: int | None = None) -> dict:
    """Seconds per recorded policy episode (at most `steps` steps; default the task's limit) with the boundary renders kept / replayed, and their ratio (median)."""
    import torch
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from worldenv_core.envs.recording import policy_episode
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.models.policy import PolicyRunner
    from worldenv_core.stage import compose_config

    if policy is None:
        cfg = compose_config("train_policy", [f"+task={suite}", "policy=small", f"task.image_size={image_size}"])
        model = instantiate(OmegaConf.to_container(cfg.policy, resolve=True), _convert_="all").eval()
    else:
        model, _ = load_checkpoint(policy, "policy")
    runner = PolicyRunner(model, sample=True, noise_scale=1.0)
    env = LiberoEnv(suite, task_id, cameras=[camera], image_size=image_size)
    rows = []
    try:
        for i in range(repeats):
            runner.generator.manual_seed(i)
            t0 = time.perf_counter()
            with torch.no_grad():
                traj = policy_episode(env, runner, i, i, steps or env.max_steps)
            rollout_s, live, took = time.perf_counter() - t0, traj.images, {}
            for kept in ((True, False) if i % 2 == 0 else (False, True)):
                traj.images = live if kept else {}
                t0 = time.perf_counter()
                to_episode(env, traj, init_state_index=i, seed=i, source="policy")
                took[kept] = rollout_s + time.perf_counter() - t0
            rows.append({"frames": len(traj.frames), "kept_s": took[True], "replayed_s": took[False]})
    finally:
        env.close()
    return {"episodes": repeats, "frames_median": statistics.median(r["frames"] for r in rows),
            "episode_s_boundaries_kept": round(statistics.median(r["kept_s"] for r in rows), 2),
            "episode_s_boundaries_replayed": round(statistics.median(r["replayed_s"] for r in rows), 2),
            "kept_over_replayed": round(statistics.median(r["kept_s"] / r["replayed_s"] for r in rows), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--suite", default="libero_object")
    parser.add_argument("--task-id", type=int, default=0)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--cameras", nargs="+", default=["agentview"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch", type=int, default=8, help="imagined rollouts per world-model call")
    parser.add_argument("--worldsim", default=None, help="a train_worldsim checkpoint (default: untrained, same cost)")
    parser.add_argument("--only", choices=["simulator", "worldsim", "policy", "robot_layer", "policy_episode"], default=None)
    parser.add_argument("--policy", default=None, help="with --only policy_episode: a policy checkpoint")
    parser.add_argument("--policies", nargs="+", default=["small", "lerobot_act"], help="policy configs (conf/policy)")
    parser.add_argument("--threads", type=int, default=1,
                        help="CPU threads for each side: the world model's torch threads and the simulator's "
                             "software renderer (Mesa llvmpipe, LP_NUM_THREADS); the same on both for a fair ratio")
    args = parser.parse_args()
    import torch

    # Before any env exists: llvmpipe reads LP_NUM_THREADS when the first GL context is made, and
    # otherwise renders on every core while torch may be held to one, which skews the ratio.
    os.environ["LP_NUM_THREADS"] = str(args.threads)
    torch.set_num_threads(args.threads)
    result = {}
    if args.only in (None, "policy"):
        result["policy"] = policy_costs(args.policies, args.suite, args.image_size, max(args.repeats, 10))
    if args.only == "policy_episode":  # minutes of rendering: asked for by name, not part of the default run
        result["policy_episode"] = policy_episode_cost(args.suite, args.task_id, args.image_size, args.cameras[0],
                                                       args.repeats, args.policy)
    if args.only not in ("worldsim", "policy", "robot_layer", "policy_episode"):
        result["simulator"] = simulator_costs(args.suite, args.task_id, args.image_size, args.cameras, args.repeats)
    if args.only in (None, "robot_layer"):
        result["robot_layer"] = robot_layer_cost(args.suite, args.task_id, args.image_size, args.cameras[0],
                                                 args.repeats, args.batch)
    if args.only not in ("simulator", "policy", "robot_layer", "policy_episode"):
        result["world_model"] = world_model_speed(args.suite, args.task_id, args.image_size, args.cameras[0],
                                                  args.repeats, args.batch, args.worldsim)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
