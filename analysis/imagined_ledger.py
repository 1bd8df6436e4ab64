"""Would ES in imagination step where the real simulator did? A kept real-route ledger replayed in the world model.

An ES iteration of the real route (`rl.policy_update=es`, `worldenv_core/rl/es.py`) keeps in its ledger every
member's real outcome from every fresh placement it met, and the members follow from the starting policy and the
ledger's seeds. This puts the same members at the same placements' first frames in the imagined environment (the
world simulator, the reflector's verdict as success: `es.imagined_member_outcomes`, what `env=imagined` ES runs)
and compares the two verdicts where it matters for ES:

* episode by episode: imagined and real success rates, the share of imagined successes that fail for real
  (the from-start hack rate) and of real successes imagination recognises;
* the step: the cosine between the pairs' differences R(+k) - R(-k) measured in imagination and for real, per
  iteration and pooled. The ARS step is the sum of the pairs' directions weighted by those differences, and
  independent Gaussian directions in a million-dimensional weight space are orthogonal to within ~1e-3, so this
  is the cosine between the step imagination would take and the one the real simulator took. About 0 (within
  +-1/sqrt(pairs)) where the world model's verdict carries none of the reward's direction, 1 where it is the
  real one. The same with the reflector's graded R where each imagined rollout ended as the return (what a
  step could follow where no imagined rollout crosses eta). No real episode is spent: the real side is the ledger's.

    python -m analysis.imagined_ledger +task=libero_spatial --ledger results/rl_recipes/es_many_pairs_seed0_ledger \\
        --policy checkpoints/libero_spatial/sft --iterations 1 10 20 --json results/rl_recipes/imagined_ledger.json

Iterations run side by side (one-thread processes, each with its own `--iterations` and `--json`) become one result
with `--merge a.json b.json --json all.json`, pooled as one run over every iteration would be.

Where the verdict is faithful (from about a third of the way into a task), the question is asked of keyframes:
`--episodes` (recorded episodes, e.g. demos or the policy's own rollouts) puts `--pairs` members drawn around
`--policy` at `--frames` keyframes per episode at `--depth`, runs each for real from there (those real episodes
are counted and printed) and in imagination, both for `--horizon` steps, and compares them the same way.

    python -m analysis.imagined_ledger +task=libero_spatial --policy checkpoints/libero_spatial/sft \\
        --episodes "data/libero_spatial/expert-*/task*/expert_000[0-1].mcap" --frames 1 --depth 0.34 0.67 --horizon 64
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic


def verdict_agreement(real: torch.Tensor, imagined: torch.Tensor) -> dict:
    """(contexts, members) real and imagined successes -> how far the imagined verdict is the real one, episode by
    episode and as the ES step's direction (members ordered as `es.antithetic_members`: pair k = 2k, 2k+1)."""
    real, imagined = real.bool(), imagined.bool()
    if real.shape != imagined.shape or real.shape[1] % 2:
        raise ValueError(f"real {tuple(real.shape)} and imagined {tuple(imagined.shape)} outcomes must be the same "
                         "(contexts, members) with members in antithetic pairs")
    d_real, d_im = pair_differences(real), pair_differences(imagined)
    hits = int((imagined & real).sum())
    return {"episodes": real.numel(), "real_success": float(real.float().mean()),
            "imagined_success": float(imagined.float().mean()),
            "agreement": float((real == imagined).float().mean()),
            "hack_rate": 1 - hits / int(imagined.sum()) if imagined.any() else float("nan"),
            "recall": hits / int(real.sum()) if real.any() else float("nan"),
            "step_cosine": cosine(d_real, d_im), "both_succeed": hits, "imagined_successes": int(imagined.sum()),
            "real_successes": int(real.sum()), "dot": float(d_real @ d_im),
            "real_by_context": real.float().mean(1).tolist(), "imagined_by_context": imagined.float().mean(1).tolist(),
            "real_sq": float(d_real @ d_real), "imagined_sq": float(d_im @ d_im)}


def pair_differences(returns: torch.Tensor) -> torch.Tensor:
    """(contexts, members) successes or rewards -> each antithetic pair's difference of their means over the
    contexts, R(+k) - R(-k)."""
    r = returns.float().mean(0).view(-1, 2)
    return r[:, 0] - r[:, 1]


def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    """NaN where either side has no step (every pair level)."""
    return cosine_of(float(a @ b), float(a @ a), float(b @ b))


def cosine_of(dot: float, sq_a: float, sq_b: float) -> float:
    """The cosine from a dot product and both squared norms (sums of them pool iterations); NaN without a step."""
    return dot / (sq_a * sq_b) ** 0.5 if sq_a * sq_b > 0 else float("nan")


def pooled(rows: list[dict]) -> dict:
    """The iterations together: the step cosine pooled as `es.half_agreement` pools its halves, rates over episodes."""
    n, real_sq = sum(r["episodes"] for r in rows), sum(r["real_sq"] for r in rows)
    imagined, real = sum(r["imagined_successes"] for r in rows), sum(r["real_successes"] for r in rows)
    hits = sum(r["both_succeed"] for r in rows)
    return {"iterations": len(rows), "episodes": n, "real_success": real / n, "imagined_success": imagined / n,
            "agreement": sum(r["agreement"] * r["episodes"] for r in rows) / n,
            "hack_rate": 1 - hits / imagined if imagined else float("nan"),
            "recall": hits / real if real else float("nan"),
            "step_cosine": cosine_of(sum(r["dot"] for r in rows), real_sq, sum(r["imagined_sq"] for r in rows)),
            **({"reward_step_cosine": cosine_of(sum(r["reward_dot"] for r in rows), real_sq,
                                                sum(r["reward_sq"] for r in rows)),
                "imagined_reward": sum(r["imagined_reward"] * r["episodes"] for r in rows) / n}
               if all("reward_dot" in r for r in rows) else {})}



# What makes two results parts of one replay: the same ledger, starting policy, models, verdict and horizon.
SAME_REPLAY = ("ledger", "policy", "worldsim", "reflector", "robot_layer", "eta", "horizon")


def merge_results(results: list[dict]) -> dict:
    """--ledger results of disjoint iterations of one replay -> one result, the iterations pooled again (the
    pooled figures come from each row's sums, so the merge equals one run over every iteration)."""
    first = results[0]
    for r in results[1:]:
        differ = [k for k in SAME_REPLAY if r.get(k) != first.get(k)]
        if differ:
            raise ConfigError(f"--merge: the results differ in {', '.join(differ)}; only parts of one replay merge")
    if not first.get("ledger"):
        raise ConfigError("--merge: only --ledger results merge (keyframe results hold one row of their own)")
    rows: dict[str, dict] = {}
    for r in results:
        twice = sorted(set(rows) & set(r["iterations"]), key=int)
        if twice:
            raise ConfigError(f"--merge: iteration(s) {', '.join(twice)} appear in two results")
        rows.update(r["iterations"])
    rows = dict(sorted(rows.items(), key=lambda kv: int(kv[0])))
    return {**first, "iterations": rows, "pooled": pooled(list(rows.values()))}


def read_result(path: Path) -> dict:
    try:
        result = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"--merge {path}: not an imagined_ledger --json result ({e})") from None
    if not isinstance(result, dict) or not {"iterations", "pooled"} <= result.keys():
        raise ConfigError(f"--merge {path}: not an imagined_ledger --json result (no iterations and pooled figures)")
    return result


def require_checkpoints(named: list[tuple[str, str]]) -> None:
    """(option, folder) pairs: each a checkpoint folder, or a one-line error naming the option, before any load."""
    for what, path in named:
        if not (Path(path) / "model.safetensors").exists():
            raise ConfigError(f"{what} {path}: no model.safetensors there (a checkpoint folder is needed)")


def placement_contexts(contract, numbers: list[int], camera: str) -> list:
    """The fresh placements a real-route iteration met (`training.placements` numbering) as imagined contexts: each
    placement's first frame rendered by the real simulator, with its proprio and instruction."""
    from stages.post_train_loop.training import placements
    from worldenv_core.envs.recording import cached_env
    from worldenv_core.envs.replay import restore
    from worldenv_core.imagination.env import Context

    start_of, out = placements(contract), []
    for k in numbers:
        start, instruction = start_of(int(k))
        env = cached_env(contract.suite, start.task_id, [camera], contract.image_size, render=True)
        frame = restore(env, start)
        image = torch.from_numpy(env.render([camera])[camera]).permute(2, 0, 1).contiguous()
        out.append(Context(task_id=start.task_id, instruction=instruction, frame=image,
                           proprio=torch.as_tensor(frame.proprio, dtype=torch.float32),
                           joint_pos=torch.as_tensor(frame.joint_pos, dtype=torch.float64)))
    return out


def line(name: str, r: dict) -> str:
    graded = (f", with the reflector's R as return {r['reward_step_cosine']:+.2f} (mean R {r['imagined_reward']:.3f})"
              if "reward_step_cosine" in r else "")
    return (f"{name}: real {r['real_success']:.2f}, imagined {r['imagined_success']:.2f}, agreement "
            f"{r['agreement']:.2f}, hack rate {r['hack_rate']:.2f}, recall {r['recall']:.2f}, "
            f"step cosine {r['step_cosine']:+.2f}{graded}")


def compare(real: torch.Tensor, out: dict) -> dict:
    """One iteration's row: the real outcomes against `es.imagined_member_outcomes`' (success and graded R)."""
    d_real, d_reward = pair_differences(real), pair_differences(out["reward"])
    return {**verdict_agreement(real, out["success"]), "imagined_reward": float(out["reward"].mean()),
            "reward_step_cosine": cosine(d_real, d_reward), "reward_dot": float(d_real @ d_reward),
            "reward_sq": float(d_reward @ d_reward), "imagined_steps": float(out["steps"].float().mean()),
            "seconds": out["timing"]}


def ledger_entries(args) -> list[dict]:
    """--ledger's entries, the --iterations asked for checked against them (before any model is loaded)."""
    from worldenv_core.rl import es

    try:
        entries = es.read_ledger(args.ledger)
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(f"--ledger {args.ledger}: {e}") from None
    bad = [i for i in args.iterations or [] if not 1 <= i <= len(entries)]
    if bad or not args.iterations:
        raise ConfigError(f"--iterations {bad or 'missing'}: the ledger holds iterations 1-{len(entries)}")
    return entries


def ledger_rows(args, entries: list[dict], contract, env, camera, encoder) -> dict:
    """--ledger: each named iteration's members around the policy its earlier steps made, at its placements."""
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.rl import es

    rows = {}
    for it in sorted(set(args.iterations)):
        e = entries[it - 1]
        policy, _ = load_checkpoint(args.policy, "policy", contract, device="cpu")
        es.replay_ledger(policy, entries, it - 1)  # the base the iteration's members were drawn around
        members = es.antithetic_members(e["seeds"], e["es_sigma"])
        out = es.imagined_member_outcomes(policy, env, placement_contexts(contract, e["contexts"], camera), members,
                                          encoder, e["es_parameters"])
        rows[it] = compare(torch.tensor(e["success"]), out)
        print(line(f"iteration {it}", rows[it]), flush=True)
    return rows


def keyframe_rows(args, contract, env, camera, encoder) -> dict:
    """--episodes: keyframes of recorded episodes (`rl.mid_episode_frames` at `rl.context_depth`) as the contexts,
    `--pairs` antithetic members around the policy drawn here, each member's real outcome from each keyframe
    collected (real episodes, counted) and its imagined one, both bounded by the imagined horizon."""
    from stages.post_train_loop.training import contexts_from_episodes
    from worldenv_core.data.mcap_io.read import glob_episode_files
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.rl import es
    from worldenv_core.rl.real_rollouts import collect_member_outcomes

    paths = glob_episode_files(args.episodes)
    if not paths:
        raise ConfigError(f"--episodes {args.episodes}: no recorded episode matches")
    contexts, starts = contexts_from_episodes(paths, camera, args.frames, tuple(args.depth), contract.chunk)
    policy, _ = load_checkpoint(args.policy, "policy", contract, device="cpu")
    g = torch.Generator().manual_seed(args.seed)
    seeds = torch.randint(2**62, (args.pairs,), generator=g).tolist()
    members = es.antithetic_members(seeds, args.sigma)
    print(f"{len(contexts)} keyframes of {len(paths)} episodes, {len(members)} members, horizon {env.horizon}: "
          f"{len(contexts) * len(members)} real episodes", flush=True)
    real = collect_member_outcomes(args.policy, contract, starts, [c.instruction for c in contexts], members, encoder,
                                   env.horizon, workers=args.workers, progress=True, journal=args.journal)
    out = es.imagined_member_outcomes(policy, env, contexts, members, encoder)
    row = {**compare(real["success"], out), "real_episodes": real["episodes"], "real_errors": real["errors"],
           "keyframes": [st.key for st in starts]}
    print(line("keyframes", row), flush=True)
    return {"keyframes": row}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", help="the run's starting policy (checkpoint folder); not with --merge")
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--ledger", type=Path, help="a real-route ES ledger (iter_NNNN.json)")
    source.add_argument("--episodes", nargs="+", help="recorded episodes (globs) whose keyframes are the contexts")
    source.add_argument("--merge", type=Path, nargs="+",
                        help="--json results of the same ledger's other iterations (e.g. run as one-thread processes "
                             "side by side): one result, pooled again, into --json")
    ap.add_argument("--iterations", type=int, nargs="+", help="with --ledger: its iterations to replay (from 1)")
    ap.add_argument("--frames", type=int, default=2, help="with --episodes: keyframes per episode")
    ap.add_argument("--depth", type=float, nargs=2, default=[1 / 3, 1.0], help="with --episodes: where they lie")
    ap.add_argument("--horizon", type=int, help="imagined (and real) steps from a context (default: the task's)")
    ap.add_argument("--pairs", type=int, default=32, help="with --episodes: antithetic pairs drawn")
    ap.add_argument("--sigma", type=float, default=0.05, help="with --episodes: the members' relative size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--journal", type=Path, help="with --episodes: keep finished real rollouts here (resume)")
    ap.add_argument("--worldsim", help="world-simulator checkpoint (default: checkpoints/<suite>/worldsim)")
    ap.add_argument("--reflector", help="reflector checkpoint (default: checkpoints/<suite>/reflector)")
    ap.add_argument("--eta", type=float, default=None, help="the verdict's threshold (default: the reflector's)")
    ap.add_argument("--robot-layer", action="store_true",
                    help="with --episodes: the robot drawn by the real renderer over imagined frames (robot_layer.py)")
    ap.add_argument("--json", type=Path, help="write the per-iteration and pooled figures here")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=...)")
    args = ap.parse_args(argv)
    if args.merge and not args.json:
        ap.error("--merge needs --json (where the merged result goes)")
    if not args.merge and not args.policy:
        ap.error("--policy is required with --ledger or --episodes")
    with user_errors():
        result = merge_results([read_result(p) for p in args.merge]) if args.merge else replay(args)
        print(line("pooled", result["pooled"]))
        if args.json:
            write_text_atomic(args.json, json.dumps(result, indent=1))
        return result


def replay(args) -> dict:
    """--ledger or --episodes: the members replayed in imagination against their real outcomes."""
    from worldenv_core.imagination.env import build_imagined_env, check_depth
    from worldenv_core.models.text import InstructionEncoder
    from worldenv_core.rl.termination import reflector_eta
    from worldenv_core.stage import compose_config, task_contract

    cfg = compose_config("post_train_loop", ["scale=small", *args.overrides])
    contract = task_contract(cfg)
    entries = ledger_entries(args) if args.ledger else None
    if not args.ledger:
        try:
            check_depth(args.depth)
        except ValueError as e:
            raise ConfigError(f"--depth: {e}") from None
    worldsim = args.worldsim or f"checkpoints/{contract.suite}/worldsim"
    reflector = args.reflector or f"checkpoints/{contract.suite}/reflector"
    require_checkpoints([("--worldsim", worldsim), ("--reflector", reflector), ("--policy", args.policy)])
    encoder = InstructionEncoder()
    if args.robot_layer and args.ledger:
        raise ConfigError("--robot-layer draws the robot in recorded scenes: it needs --episodes' keyframes")
    env, camera = build_imagined_env(worldsim, reflector, reflector_eta(reflector, args.eta), encoder,
                                     args.horizon or contract.max_steps, None, "cpu", contract,
                                     robot_layer=args.robot_layer)
    rows = (ledger_rows(args, entries, contract, env, camera, encoder) if args.ledger else
            keyframe_rows(args, contract, env, camera, encoder))
    return {"ledger": str(args.ledger) if args.ledger else None, "episodes": args.episodes, "policy": args.policy,
            "worldsim": worldsim, "robot_layer": args.robot_layer, "reflector": reflector, "eta": env.eta,
            "horizon": env.horizon, "iterations": rows, "pooled": pooled(list(rows.values()))}


if __name__ == "__main__":
    main()
