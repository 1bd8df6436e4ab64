"""Stage `post_train_loop`: LOOP (RLOO + PPO) post-training inside the world model (paper
sec. 4.3, Algorithm 1).

Every iteration freezes a behaviour copy of the policy, samples `contexts_per_iteration`
contexts (first frame, proprio and instruction of collected episodes: fresh seeded placements,
never the benchmark init states that evaluation uses), runs N imagined rollouts per context
with Laplace-sampled actions until the reflector's R > eta or the horizon, computes RLOO
advantages from R at t_end, and takes `ppo_epochs` passes of the clipped objective. Every
`eval.every` iterations (and before the first) the policy is measured in the real simulator.
"""

from __future__ import annotations

import copy
import json
import logging
import time
from pathlib import Path

import torch
from omegaconf import DictConfig
from tqdm import tqdm

from worldenv_core.data.mcap_io import read_episode
from worldenv_core.data.selection import MissingEpisodesError, collected_episodes
from worldenv_core.envs.collection import PolicyEvalJob, evaluate_policy_task
from worldenv_core.envs.imagined import ImaginedSimulator
from worldenv_core.envs.tasks import get_task, resolve_task_ids
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.manifest import StageRun
from worldenv_core.models.checkpoint import read_config, save_model
from worldenv_core.models.policy import load_policy
from worldenv_core.models.reflector import check_eta, load_reflector, reflector_eta
from worldenv_core.models.text import InstructionEncoder
from worldenv_core.parallel import run_jobs
from worldenv_core.rl.imagined_env import Context, ImaginedEnv
from worldenv_core.rl.imagined_recording import record_imagined_rollouts, write_imagined_rollouts
from worldenv_core.rl.loop import collect_rollouts, policy_param_groups, ppo_update
from worldenv_core.stage import (ConfigError, positive_int, require_task, resolve_checkpoint, resolve_policy, work_dir,
                                 resolved, start)
from worldenv_core.tracking import make_tracker
from worldenv_core.training import Checkpoints, pick_device, plot_history

log = logging.getLogger("worldenv.post_train_loop")
# Measured at evaluations (the tracker's "eval/" group); the rest of an iteration's entry is training.
EVAL_KEYS = ("real_success", "imagined_reward", "imagined_success", "imagined_real_gap")


def with_gap(entry: dict) -> dict:
    """The imagined-vs-real gap where both were measured: the reflector's imagined success rate on
    the fixed contexts minus the real success rate (positive: imagination is too generous)."""
    if "real_success" in entry and "imagined_success" in entry:
        entry["imagined_real_gap"] = entry["imagined_success"] - entry["real_success"]
    return entry


def validate(cfg: DictConfig) -> None:
    require_task(cfg)
    for key in ("rl.iterations", "rl.contexts_per_iteration", "rl.ppo_epochs", "rl.minibatch", "rl.horizon"):
        positive_int(cfg, key)
    positive_int(cfg, "eval.every", allow_zero=True)
    positive_int(cfg, "eval.init_states")
    positive_int(cfg, "eval.imagined_contexts", allow_zero=True)
    positive_int(cfg, "eval.record_contexts", allow_zero=True)
    if cfg.eval.imagined_contexts and cfg.eval.imagined_rollouts < 2:
        raise ConfigError(f"eval.imagined_rollouts must be at least 2, got {cfg.eval.imagined_rollouts}")
    if not isinstance(cfg.rl.n_rollouts, int) or cfg.rl.n_rollouts < 2:
        raise ConfigError(f"rl.n_rollouts must be at least 2 (the RLOO baseline averages the other N - 1), "
                          f"got {cfg.rl.n_rollouts}")
    try:
        if cfg.rl.eta is not None:  # null: the reflector's own
            check_eta(cfg.rl.eta)
    except ValueError as e:
        raise ConfigError(f"rl.{e}") from None
    if not cfg.rl.epsilon > 0:
        raise ConfigError(f"rl.epsilon (the PPO clip) must be > 0, got {cfg.rl.epsilon}")
    if not (cfg.rl.lr_backbone > 0 and cfg.rl.lr_heads > 0):
        raise ConfigError("rl.lr_backbone and rl.lr_heads must be > 0")


def contexts_from_episodes(paths: list[Path], camera: str) -> list[Context]:
    out = []
    for p in paths:
        ep = read_episode(p, cameras=[camera])
        out.append(Context(task_id=ep.meta.task_id, instruction=ep.meta.instruction,
                           frame=torch.from_numpy(ep.images[camera][0]).permute(2, 0, 1).contiguous(),
                           proprio=torch.from_numpy(ep.proprio[0])))
    return out


def build_env(cfg, worldsim_path: str, reflector_path: str, eta: float, encoder, device) -> tuple[ImaginedEnv, str]:
    meta = read_config(worldsim_path)["meta"]
    contract = {"image_size": cfg.task.image_size, "chunk": cfg.task.chunk}
    cameras = {int(t): PinholeCamera.from_dict(c) for t, c in meta["cameras"].items()}
    sim = ImaginedSimulator.from_checkpoint(worldsim_path, min(cameras), cfg.rl.sampling_steps, device, expect=contract)
    reflector, rmeta = load_reflector(reflector_path, expect={"image_size": cfg.task.image_size}, device=str(device))
    if rmeta["camera"] != meta["camera"]:
        raise ConfigError(f"the reflector watches {rmeta['camera']!r} but the world simulator imagines {meta['camera']!r}")
    return ImaginedEnv(sim, cameras, reflector, encoder, eta, cfg.rl.horizon), meta["camera"]


def imagined_success(policy, env, contexts: list[Context], cfg, encoder) -> dict:
    """The policy in imagination on a fixed set of contexts with fixed noise: the same rollouts'
    worth of randomness for the SFT and every later policy, so the numbers are comparable and
    show whether post-training improved the objective it optimises (mean reward, reflector
    success rate), whatever the real simulator says."""
    n = min(cfg.eval.imagined_contexts, len(contexts))
    g = torch.Generator().manual_seed(cfg.seed + 7_777)
    picks = torch.randperm(len(contexts), generator=g)[:n].tolist()
    with torch.no_grad():
        batch = collect_rollouts(policy, env, [contexts[i] for i in picks], cfg.eval.imagined_rollouts, encoder,
                                 generator=g)
    return {"imagined_reward": float(batch.rewards.mean()),
            "imagined_success": float(batch.by_reflector.float().mean())}


def record_imagined(policy, env, contexts: list[Context], cfg, encoder, camera: str, out_dir: Path,
                    extra: dict) -> list[Path]:
    """A few imagined rollouts of the policy, every frame, written as MCAP episodes (the same
    fixed contexts and noise at every evaluation, so the files show what training changed)."""
    n = min(cfg.eval.record_contexts, len(contexts))
    g = torch.Generator().manual_seed(cfg.seed + 9_999)
    picks = torch.randperm(len(contexts), generator=g)[:n].tolist()
    names = {t: get_task(cfg.task.suite, t).name for t in {contexts[i].task_id for i in picks}}
    rollouts = record_imagined_rollouts(policy, env, [contexts[i] for i in picks], 2, encoder, cfg.task.suite, names,
                                        camera, extra=extra, generator=g, fps=float(cfg.task.control_freq))
    return write_imagined_rollouts(rollouts, out_dir, env.eta)


def real_success(cfg, policy_path: str) -> float:
    """Success in the real simulator (oracle termination) on the first benchmark init states."""
    task = cfg.task
    jobs = [PolicyEvalJob(policy_path=policy_path, suite=task.suite, task_id=t, init_ids=tuple(range(cfg.eval.init_states)),
                          cameras=tuple(task.cameras), image_size=task.image_size, chunk=task.chunk,
                          max_steps=task.max_steps, termination="oracle")
            for t in resolve_task_ids(task.suite, task.task_ids)]
    rows = [r for out in run_jobs(evaluate_policy_task, jobs, workers=cfg.eval.workers, desc="real-sim eval",
                                  progress=cfg.progress, unit="task") for r in out["rows"]]
    return sum(r["success"] for r in rows) / len(rows)


def run(cfg: DictConfig) -> dict:
    manifest = start(cfg, validate)
    task, rl = cfg.task, cfg.rl
    device = pick_device(cfg.device)
    config = resolved(cfg)
    tags = {"task": task.name, "scale": cfg.scale.name, "eta": None if rl.eta is None else float(rl.eta),
            "n_rollouts": int(rl.n_rollouts)}
    with StageRun(manifest, "post_train_loop", tags, config) as stage:
        policy_path = resolve_policy(cfg, stage)
        worldsim_path = resolve_checkpoint(stage, cfg.worldsim_from, "train_worldsim", task.name, cfg.scale.name)
        reflector_path = resolve_checkpoint(stage, cfg.reflector_from, "train_reflector", task.name, cfg.scale.name)
        encoder = InstructionEncoder()
        eta = reflector_eta(reflector_path, rl.eta)
        stage.record.tags["eta"] = eta  # the threshold used, also when it is the reflector's own
        env, camera = build_env(cfg, worldsim_path, reflector_path, eta, lambda s: encoder(s).to(device), device)
        policy, pmeta = load_policy(policy_path, expect={"image_size": task.image_size, "chunk": task.chunk},
                                    device=str(device))
        if policy.cameras != [camera]:
            raise ConfigError(f"the policy looks at {policy.cameras}, but the world simulator imagines only {camera!r}")
        try:
            paths = collected_episodes(manifest, stage, task.name, cfg.scale.name, cfg.expert_only)
        except MissingEpisodesError as e:
            raise ConfigError(str(e)) from None
        contexts = contexts_from_episodes(paths, camera)
        # The work dir (what resume finds) is named by what defines the training and by its inputs,
        # not by how it is evaluated or shown: changing eval.* or progress continues the same run.
        work = work_dir(cfg.experiment_dir, "post_train_loop",
                        {k: v for k, v in config.items() if k not in ("eval", "progress")}, stage.work_inputs())
        stage.lock(work)  # one run at a time trains into a work dir
        policy_cfg = read_config(policy_path)["model"]
        optimizer = torch.optim.Adam(policy_param_groups(policy, rl.lr_backbone, rl.lr_heads))
        ckpts = Checkpoints(work)
        start_it, history = ckpts.restore(policy, {"ppo": optimizer})
        meta = {**pmeta, "post_trained_from": policy_path, "worldsim": worldsim_path, "reflector": reflector_path}
        log.info("post-training %s for %d iterations: %d contexts x %d rollouts each, eta %.2f, on %s; work dir %s",
                 policy_path, rl.iterations, rl.contexts_per_iteration, rl.n_rollouts, eta, device, work)
        encode = lambda s: encoder(s).to(device)  # noqa: E731
        imagine = (lambda: imagined_success(policy, env, contexts, cfg, encode)) if cfg.eval.imagined_contexts else dict
        tracker = make_tracker(cfg, work, "post_train_loop", config)
        provenance = {"policy": policy_path, "worldsim": worldsim_path, "reflector": reflector_path}

        def record(iteration: int) -> None:  # a sample of imagined rollouts to look at
            if cfg.eval.record_contexts:
                record_imagined(policy, env, contexts, cfg, encode, camera, work / "imagined" / f"iter_{iteration:04d}",
                                {**provenance, "iteration": str(iteration)})

        if start_it == 0:
            history.append(with_gap({"step": 0, **imagine(), **({"real_success": real_success(cfg, policy_path)}
                                                                if cfg.eval.every else {})}))
            tracker.log(history[-1], 0, group="eval")
            log.info("SFT policy: %s", json.dumps(history[-1]))
            record(0)
        t0 = time.perf_counter()
        bar = tqdm(range(start_it, rl.iterations), initial=start_it, total=rl.iterations, desc="post_train_loop",
                   disable=not cfg.progress, dynamic_ncols=True)
        for it in bar:
            g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + it)  # rollouts, contexts, minibatches
            picks = torch.randint(len(contexts), (rl.contexts_per_iteration,), generator=g).tolist()
            behaviour = copy.deepcopy(policy).eval()  # Algorithm 1 line 3: the frozen behaviour policy
            t_it = time.perf_counter()
            batch = collect_rollouts(behaviour, env, [contexts[i] for i in picks], rl.n_rollouts, encode, generator=g)
            stats = ppo_update(policy, optimizer, batch, rl.ppo_epochs, rl.epsilon, rl.minibatch, generator=g)
            entry = {"step": it + 1, "mean_reward": float(batch.rewards.mean()),
                     "reflector_success_rate": float(batch.by_reflector.float().mean()),
                     "episode_length": float(batch.t_end.float().mean()), "mean_beta": batch.beta_mean,
                     **stats, "seconds": time.perf_counter() - t_it}
            done = it + 1
            path = ckpts.save(done, policy, policy_cfg, {**meta, "iteration": done}, {"ppo": optimizer}, history + [entry])
            if done == rl.iterations or (cfg.eval.every and done % cfg.eval.every == 0):
                entry.update(imagine())
            if cfg.eval.every and (done % cfg.eval.every == 0 or done == rl.iterations):
                entry["real_success"] = real_success(cfg, str(path))
                with_gap(entry)
                ckpts.save(done, policy, policy_cfg, {**meta, "iteration": done}, {"ppo": optimizer}, history + [entry])
            if done == rl.iterations or (cfg.eval.every and done % cfg.eval.every == 0):
                record(done)
            history.append(entry)
            tracker.log({k: v for k, v in entry.items() if k not in EVAL_KEYS}, done, group="train")
            tracker.log({k: v for k, v in entry.items() if k in EVAL_KEYS}, done, group="eval")
            bar.set_postfix(reward=f"{entry['mean_reward']:.3f}", stop=f"{entry['reflector_success_rate']:.2f}",
                            kl=f"{entry['approx_kl']:.4f}")
            log.info("iteration %d: %s", done, json.dumps({k: round(v, 4) for k, v in entry.items()}))
        bar.close()
        tracker.close()
        final = save_model(work / "policy", policy.cpu(), policy_cfg, {**meta, "iteration": rl.iterations})
        for f in sorted(final.iterdir()):
            stage.add_output(f, kind="checkpoint")
        stage.add_output(plot_history(history, work / "training.png", f"post_train_loop {task.name}"), kind="plot")
        stage.add_output(work / "training.json", kind="report")
        for path in sorted((work / "imagined").glob("iter_*/*.mcap")):  # every sitting's, also before a resume
            stage.add_output(path, kind="imagined")  # the per-iteration log beside the plot, for the report
        evals = [h for h in history if "real_success" in h]
        stage.metrics.update({"iterations": rl.iterations, "train_wall_s": round(time.perf_counter() - t0, 1),
                              "device": str(device), "final_mean_reward": history[-1].get("mean_reward"),
                              "real_success": {str(h["step"]): h["real_success"] for h in evals},
                              "imagined_reward": {str(h["step"]): h["imagined_reward"] for h in history
                                                  if "imagined_reward" in h},
                              "imagined_success": {str(h["step"]): h["imagined_success"] for h in history
                                                   if "imagined_success" in h}})
        log.info("post-trained policy saved to %s; metrics %s", final, json.dumps(stage.metrics))
    return stage.metrics
