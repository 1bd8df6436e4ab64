"""Would a critic help LOOP? Measured offline on two iterations' real rollouts, before a run is spent on it.

A critic (`worldenv_core.rl.critic`) is fitted to the rollouts of one iteration (`--fit`: a rollout
journal, the folder of `<digest>.rollout` files that `post_train_loop env=real` keeps while an
iteration runs, with its behaviour policy in `<folder>_behaviour` or `--fit-policy`) and judged on
the next iteration's (`--judge`; the same journal: fitted to its even groups, judged on its odd ones),
which it never saw, as the stage would use it: its cross-entropy
against the constant predictor's, its AUROC by depth into the rollout, and above all the policy
gradient of the judged batch's mixed groups with RLOO's one advantage per rollout against the
critic's per-chunk advantages (GAE, gamma 1, each lambda): the signal and the noise per group
(`loop.gradient_signal`) and the groups a batch needs for its direction to have cosine 0.9 with the
reward's. The critic pays only if that number falls well below RLOO's.

    python -m analysis.critic_probe +task=libero_spatial --fit outputs/journal_copies/<iteration k> \\
        --judge outputs/journal_copies/<iteration k+1> --json results/rl_recipes/critic_probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import zlib
from pathlib import Path

import torch

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.files import write_text_atomic
from worldenv_core.stats import auroc


def read_journal(folder: Path, n_rollouts: int) -> list[dict]:
    """A journal's finished rollouts in batch order, whole groups of N only."""
    runs = {}
    for path in sorted(folder.glob("*.rollout")):
        _, result = pickle.loads(zlib.decompress(path.read_bytes()))
        runs[result["index"]] = result
    groups = {}
    for i, r in runs.items():
        groups.setdefault(i // n_rollouts, []).append(r)
    whole = [sorted(g, key=lambda r: r["index"]) for _, g in sorted(groups.items()) if len(g) == n_rollouts]
    if len(whole) < 2:
        raise ConfigError(f"{folder}: {len(whole)} whole groups of {n_rollouts} rollouts; the probe needs at least 2")
    return [r for g in whole for r in g]


def start_outcomes(runs: list[dict]) -> dict[str, list[int]]:
    """Each start's [successes, rollouts] in a journal's rollouts."""
    out: dict[str, list[int]] = {}
    for r in runs:
        row = out.setdefault(r["start"].key, [0, 0])
        row[0] += int(r["error"] is None and r["first_success"] is not None)
        row[1] += 1
    return out


def load_batch(folder: Path, policy_dir: Path | None, contract, encoder, n_rollouts: int, noise_scale: float,
               exploration: str = "step"):
    from worldenv_core.envs.tasks import get_task
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.rl.real_rollouts import batch_from_runs

    policy_dir = policy_dir or folder.with_name(folder.name + "_behaviour")
    if not (policy_dir / "model.safetensors").exists():
        raise ConfigError(f"no behaviour policy for {folder}: {policy_dir} has no model.safetensors")
    policy = load_checkpoint(policy_dir, "policy", contract)[0].eval()
    runs = read_journal(folder, n_rollouts)
    lang = encoder([get_task(contract.suite, r["start"].task_id).instruction for r in runs]).float().cpu()
    return policy, batch_from_runs(runs, policy, contract, lang, n_rollouts, noise_scale, exploration)


def by_depth(values, targets, cc, horizon_chunks: int, bins: int = 4) -> list[dict]:
    """AUROC of V against the eventual success, chunks binned by depth into the horizon."""
    out = []
    for b in range(bins):
        lo, hi = b * horizon_chunks / bins, (b + 1) * horizon_chunks / bins
        sel = (cc >= lo) & (cc < hi)
        t = targets[sel]
        out.append({"depth": f"{b}/{bins}-{b + 1}/{bins}", "chunks": int(sel.sum()),
                    "auroc": auroc(values[sel].tolist(), t.tolist()) if 0 < t.sum() < len(t) else float("nan")})
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("overrides", nargs="*", help="the post_train_loop settings of the run (+task=..., scale=...)")
    ap.add_argument("--fit", required=True, type=Path, help="the journal the critic is fitted to (iteration k)")
    ap.add_argument("--judge", required=True, type=Path, help="the journal it is judged on (iteration k+1)")
    ap.add_argument("--fit-policy", type=Path, help="the behaviour of --fit (default <fit>_behaviour)")
    ap.add_argument("--judge-policy", type=Path, help="the behaviour of --judge (default <judge>_behaviour)")
    ap.add_argument("--lambdas", type=float, nargs="+", default=[1.0, 0.95, 0.8, 0.5])
    ap.add_argument("--steps", type=int, default=2000, help="critic fitting steps")
    ap.add_argument("--minibatch", type=int, default=256)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--outcomes", type=Path, help="also write each start's successes out of N in both journals (JSON): "
                                                  "what a placement pool's revisits are compared with, kept small")
    args = ap.parse_args(argv)
    with user_errors():
        from worldenv_core.models.text import InstructionEncoder
        from worldenv_core.rl.critic import (ChunkCritic, chunk_features, chunk_values, constant_bce, critic_bce, fit_critic,
                                             gae_advantages)
        from worldenv_core.rl.loop import direction_cosine, informative_groups, select
        from worldenv_core.stage import compose_config, task_contract

        torch.manual_seed(args.seed)
        cfg = compose_config("post_train_loop", ["scale=small", *args.overrides])
        contract, rl = task_contract(cfg), cfg.rl
        n, drawn = int(rl.n_rollouts), (float(rl.get("noise_scale", 1.0)), rl.get("exploration", "step"))  # how actions were drawn
        encoder = InstructionEncoder()
        if args.outcomes:
            write_text_atomic(args.outcomes, json.dumps({str(f): start_outcomes(read_journal(f, n))
                                                          for f in (args.fit, args.judge)}, indent=1))
        fit_policy, fit_batch = load_batch(args.fit, args.fit_policy, contract, encoder, n, *drawn)
        if args.judge.resolve() == args.fit.resolve():  # one journal: fitted to its even groups, judged on its odd ones
            group = torch.arange(len(fit_batch.rewards)) // n
            judge_policy, judge_batch, fit_batch = fit_policy, select(fit_batch, group % 2 == 1), select(fit_batch, group % 2 == 0)
        else:
            judge_policy, judge_batch = load_batch(args.judge, args.judge_policy, contract, encoder, n, *drawn)
        horizon_chunks = -(-int(rl.horizon) // contract.chunk)
        f_fit, rr_fit, cc_fit = chunk_features(fit_policy, fit_batch)
        f_judge, rr_judge, cc_judge = chunk_features(judge_policy, judge_batch)
        critic = ChunkCritic(f_fit.shape[1], horizon_chunks)
        opt = torch.optim.Adam(critic.parameters(), lr=args.lr)
        g = torch.Generator().manual_seed(args.seed)
        fitted = fit_critic(critic, opt, f_fit, cc_fit, fit_batch.rewards[rr_fit], args.steps, args.minibatch, g)
        targets = judge_batch.rewards[rr_judge]
        constant = constant_bce(targets)
        live = judge_batch.mask[:, :, 0] > 0
        values = chunk_values(critic, f_judge, rr_judge, cc_judge, tuple(live.shape))
        keep = informative_groups(judge_batch, n, None)
        rows = []
        for name, adv in [("rloo", judge_batch.advantages),
                          *[(f"gae_{lam:g}", gae_advantages(values, live, judge_batch.rewards, lam)) for lam in args.lambdas]]:
            batch = select(dataclasses.replace(judge_batch, advantages=adv), keep)
            d = direction_cosine(judge_policy, batch, n, float(rl.epsilon)) or {}
            rows.append({"advantages": name, **{k: d.get(k) for k in ("direction_cosine", "gradient_signal_sq",
                                                                       "gradient_noise_sq", "groups_for_cos_0.9")}})
            print(f"{name:10s} cosine {d.get('direction_cosine', float('nan')):+.3f}  signal {d.get('gradient_signal_sq', 0):.3g}"
                  f"  noise {d.get('gradient_noise_sq', 0):.3g}  groups for cos 0.9 {d.get('groups_for_cos_0.9', float('inf')):.3g}")
        out = {"fit": str(args.fit), "judge": str(args.judge), "fit_rollouts": len(fit_batch.rewards),
               "judge_rollouts": len(judge_batch.rewards), "mixed_groups": int(keep.sum()) // n,
               "judge_success": float(judge_batch.rewards.mean()), **fitted,
               "judge_bce": critic_bce(critic, f_judge, cc_judge, targets), "constant_bce": constant,
               "auroc_by_depth": by_depth(values[rr_judge, cc_judge], targets, cc_judge, horizon_chunks),
               "gradients": rows}
        print(f"critic on unseen rollouts: BCE {out['judge_bce']:.3f} (constant {constant:.3f}); AUROC by depth "
              + ", ".join(f"{d['depth']} {d['auroc']:.2f}" for d in out["auroc_by_depth"]))
        if args.json:
            write_text_atomic(args.json, json.dumps(out, indent=1, default=float))
        return out


if __name__ == "__main__":
    main()
