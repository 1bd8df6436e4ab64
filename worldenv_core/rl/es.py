"""Exploration in weight space: antithetic evolution strategies (ARS) with the true reward.

Why this update exists (docs/post_training.md#evolution-strategies-in-weight-space): LOOP explores by
drawing each executed action from Laplace(mu, e^beta). For this project's policy that noise is white, a
few hundredths of the action's spread per step, and the next chunk's closed loop corrects most of it, so
whether a rollout succeeds barely depends on which noise was drawn: the policy gradient measured as noise
at every batch the real route affords (results/rl_campaign.md). Here a rollout's *weights* are
perturbed once and it then acts with its mean actions: the change is systematic, the same in every
state of the episode and in every start, and an iteration compares whole behaviours on the same
contexts. The update is Augmented Random Search (Mania et al. 2018, V1-t without state normalisation):

    theta += step / (b sigma_R) * sum over the b best pairs of (R(+k) - R(-k)) n_k

where the pair k's members are theta +- sigma n_k, n_k ~ N(0, I) scaled per tensor by that tensor's
RMS (so sigma is a relative size), R a member's mean return over the iteration's contexts (every
member sees the same contexts: their difficulty cancels in the difference), sigma_R the spread of the
2b returns used. A direction is named by its seed: any process rebuilds a member from the base weights
and (seed, signed sigma), so workers load one checkpoint per iteration and a run's weights follow from
its starting policy and the seeds it drew.
"""

from __future__ import annotations

import torch

PARAMETER_SETS = ("mean", "heads")  # which weights move: every one the mean action reads, or trunk + action head
RMS_FLOOR = 1e-3  # a tensor initialised at zero (a bias) still explores


def es_parameters(policy: torch.nn.Module, which: str = "mean") -> list[tuple[str, torch.nn.Parameter]]:
    """The perturbed parameters, in a fixed order. mean: all but the scale head (members act with their
    mean actions, so the scale is never read); heads: the trunk and the action head only."""
    if which not in PARAMETER_SETS:
        raise ValueError(f"rl.es_parameters must be one of {list(PARAMETER_SETS)}, got {which!r}")
    out = []
    for name, p in policy.named_parameters():
        if name.startswith("scale_head."):
            continue
        if which == "heads" and not name.startswith(("trunk.", "action_head.")):
            continue
        out.append((name, p))
    if not out:
        raise ValueError(f"the policy has no parameter in the set {which!r}")
    return out


def directions(policy: torch.nn.Module, seed: int, which: str = "mean") -> list[torch.Tensor]:
    """The direction named by `seed`: one N(0, 1) draw per parameter element, each tensor scaled by its
    own RMS (floored), drawn in `es_parameters` order from one generator."""
    g = torch.Generator().manual_seed(int(seed))
    out = []
    for _, p in es_parameters(policy, which):
        rms = p.detach().float().pow(2).mean().sqrt().clamp_min(RMS_FLOOR)
        out.append(torch.randn(p.shape, generator=g) * rms)
    return out


@torch.no_grad()
def perturb(policy: torch.nn.Module, seed: int, coef: float, which: str = "mean") -> torch.nn.Module:
    """In place: theta += coef * direction(seed). Returns the policy. The direction is computed from the
    weights as they are before the move, so a member is rebuilt exactly from its base and (seed, coef)."""
    params = es_parameters(policy, which)
    for (_, p), d in zip(params, directions(policy, seed, which)):
        p.add_(d.to(p.device, p.dtype), alpha=float(coef))
    return policy


def antithetic_members(seeds: list[int], sigma: float) -> list[tuple[int, float]]:
    """[(seed, +sigma), (seed, -sigma)] for each seed: member 2k and 2k+1 are pair k."""
    if not sigma > 0:
        raise ValueError(f"rl.es_sigma must be > 0, got {sigma}")
    return [(int(s), sign * float(sigma)) for s in seeds for sign in (1.0, -1.0)]


def context_returns(success: torch.Tensor, steps: torch.Tensor, discount: float = 1.0,
                    score: torch.Tensor | None = None) -> torch.Tensor:
    """(contexts, members) outcomes -> each rollout's return: discount**steps for a success (1 with discount 1:
    the benchmark's success), 0 for a failure. `score` (the imagined route's `rl.es_return=score`): the reflector's
    R where the rollout ended takes the success's place, so a rollout that came closer to success returns more
    although no member crossed the threshold."""
    if not 0 < discount <= 1:
        raise ValueError(f"rl.es_discount must be in (0, 1], got {discount}")
    value = success.float() if score is None else score.float()
    return value * torch.as_tensor(discount, dtype=torch.float64).pow(steps.double()).float()


def member_returns(success: torch.Tensor, steps: torch.Tensor, discount: float = 1.0,
                   score: torch.Tensor | None = None) -> torch.Tensor:
    """(contexts, members) outcomes -> each member's mean return over the contexts (`context_returns`)."""
    return context_returns(success, steps, discount, score).mean(0)


def pair_stats(seeds: list[int], returns: torch.Tensor,
               top: int | None = None) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The pairs a step uses (`ars_update`'s `top`), their differences R(+k) - R(-k), and the figures of
    the members' returns (the spread sigma_R over the pairs used, best and worst member)."""
    r = returns.view(len(seeds), 2).float()
    b = len(seeds) if top is None else max(1, min(int(top), len(seeds)))
    best = r.max(1).values.argsort(descending=True, stable=True)[:b]
    used = r[best]
    diff = used[:, 0] - used[:, 1]
    stats = {"es_pairs": float(len(seeds)), "es_pairs_used": float(b),
             "es_return_std": float(used.flatten().std(unbiased=False)),
             "es_member_best": float(r.max()), "es_member_worst": float(r.min()),
             "es_pair_diff_abs": float(diff.abs().mean())}
    return stats, best, diff


@torch.no_grad()
def ars_update(policy: torch.nn.Module, seeds: list[int], returns: torch.Tensor, step: float, top: int | None = None,
               which: str = "mean") -> dict:
    """One ARS step from the members' returns (2 per seed, + then -, as `antithetic_members` orders
    them). `top`: use the b pairs whose better member did best (ARS V1-t); None: every pair. No step
    when the returns used do not differ (nothing to follow). -> figures of the step."""
    if not step > 0:
        raise ValueError(f"rl.es_step must be > 0, got {step}")
    stats, best, diff = pair_stats(seeds, returns, top)
    b, sigma_r = len(best), stats["es_return_std"]
    if sigma_r == 0.0:
        return {**stats, "es_step_rms": 0.0}
    params = es_parameters(policy, which)
    total = [torch.zeros_like(p) for _, p in params]
    for k, w in zip(best.tolist(), (diff / (b * sigma_r)).tolist()):
        for acc, d in zip(total, directions(policy, seeds[k], which)):
            acc.add_(d.to(acc.device, acc.dtype), alpha=w)
    moved = sq = 0.0
    for (_, p), acc in zip(params, total):
        rms = p.detach().float().pow(2).mean().sqrt().clamp_min(RMS_FLOOR)
        p.add_(acc, alpha=float(step))
        sq += float((acc * step / rms).pow(2).sum())
        moved += acc.numel()
    return {**stats, "es_step_rms": (sq / moved) ** 0.5}  # the step's size relative to each tensor's RMS


LEDGER_SETTINGS = ("es_sigma", "es_step", "es_top", "es_discount", "es_parameters", "es_return")
# what a ledger written before a setting existed was made with
LEDGER_DEFAULTS = {"es_return": "success"}
RETURNS = ("success", "score")  # rl.es_return
SCORE_APART = 0.05  # two members' graded returns from one context this far apart tell them apart (`mixed_contexts`)


def mixed_contexts(values: torch.Tensor, apart: float = 0.0) -> int:
    """(contexts, members) outcomes or returns (`context_returns`) -> how many contexts told any two members
    apart: the starts a step's direction is learnt from (one where every member succeeded, or every one failed,
    says nothing). With a discounted return, members that all succeeded are told apart by when; with the graded
    score (`rl.es_return=score`), by a spread above `apart` (`SCORE_APART`)."""
    v = values.float()
    return int(((v.max(1).values - v.min(1).values) > apart).sum())


def write_ledger_entry(folder, iteration: int, contexts: list[int], seeds: list[int], success: torch.Tensor,
                       steps: torch.Tensor, returns: torch.Tensor, rl, rolled_back: bool = False,
                       no_step: bool = False, score: torch.Tensor | None = None,
                       focus_task: int | None = None) -> None:
    """One iteration's record (whole or absent): its contexts, directions, every member's outcome from every
    context (contexts x members) and the settings of its step, enough to redo the step (`replay_ledger`);
    `rolled_back`: the step was made and undone (the paired-replay guard); `no_step`: none was made (too few
    contexts told the members apart, `rl.es_min_mixed`); a replay skips both. `score`: the reflector's R where
    each rollout ended (`rl.es_return=score`), kept beside the verdicts. `focus_task`: the position (in the
    tasks trained on) of the one task the iteration trained under `rl.task_focus=1`, kept because the focus counts
    from 0 and the ledger from 1 (iteration 1 is position 0), which is easy to misread."""
    import json
    from pathlib import Path

    from worldenv_core.files import write_text_atomic

    entry = {"iteration": int(iteration), "contexts": [int(c) for c in contexts], "seeds": [int(s) for s in seeds],
             "success": success.int().tolist(), "steps": steps.int().tolist(), "returns": returns.tolist(),
             **({"score": [[round(float(v), 4) for v in row] for row in score.tolist()]} if score is not None else {}),
             **{k: rl.get(k, LEDGER_DEFAULTS.get(k)) for k in LEDGER_SETTINGS},
             **({"focus_task": int(focus_task)} if focus_task is not None else {}),
             **({"rolled_back": True} if rolled_back else {}),
             **({"no_step": True} if no_step else {})}
    Path(folder).mkdir(parents=True, exist_ok=True)
    write_text_atomic(Path(folder) / f"iter_{int(iteration):04d}.json", json.dumps(entry))


START_FILE = "start.json"  # in a campaign's ledger folder: the weights its steps were made on


def weights_digest(policy: torch.nn.Module) -> str:
    """sha256 (16 hex digits) over a policy's weights and buffers, by name: what a ledger's steps were made on."""
    import hashlib

    h = hashlib.sha256()
    for name, t in policy.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def record_start(folder, digest: str) -> None:
    """Name the starting weights in a ledger folder, once (its first export)."""
    import json
    from pathlib import Path

    from worldenv_core.files import write_text_atomic

    path = Path(folder) / START_FILE
    if not path.exists():
        write_text_atomic(path, json.dumps({"weights": digest}))


def check_start(folder, digest: str) -> None:
    """A ledger's steps replay onto the weights it started from; on others they would silently make another
    policy (a retrained SFT on a fresh machine, a wrong `policy_from`). ValueError naming both digests; a folder
    from before the record (no start.json) is taken as it is."""
    import json
    from pathlib import Path

    path = Path(folder) / START_FILE
    if path.exists() and (want := json.loads(path.read_text())["weights"]) != digest:
        raise ValueError(f"its steps were made on starting weights {want}, and this starting policy's are {digest}: "
                         "replayed on it they would make another policy (start a new ledger for it)")


def read_ledger(folder) -> list[dict]:
    """A ledger's entries in iteration order; a gap (an iteration missing) is an error."""
    import json
    from pathlib import Path

    entries = [json.loads(p.read_text()) for p in sorted(Path(folder).glob("iter_*.json"))]
    for i, e in enumerate(entries, 1):
        if e["iteration"] != i:
            raise ValueError(f"{folder}: iteration {i} is missing from the ledger (found {e['iteration']})")
    return entries


@torch.no_grad()
def replay_ledger(policy: torch.nn.Module, entries: list[dict], upto: int | None = None) -> torch.nn.Module:
    """The starting policy moved by the ledger's steps (in place), iterations 1..upto: the run's weights
    rebuilt from a few kilobytes, on any machine that has the starting policy."""
    for e in entries[:upto]:
        if e.get("rolled_back") or e.get("no_step"):  # made, then undone by the guard; or never made
            continue
        ars_update(policy, e["seeds"], torch.tensor(e["returns"]), e["es_step"], e["es_top"], e["es_parameters"])
    return policy


def halves(contexts: list[int], n_tasks: int, across_tasks: bool = False) -> torch.Tensor:
    """Each context's half (0 or 1) for `half_agreement`. Contexts numbered as fresh placements are of task
    number mod `n_tasks` (`stages.post_train_loop.training.placements`), and consecutive numbers cycle through
    the tasks, so even and odd positions would be two different sets of tasks. Within tasks (the default): each
    task's contexts alternate between the halves, so both hold every task. `across_tasks`: the tasks at even
    positions against those at odd ones."""
    if across_tasks:
        return torch.tensor([(int(c) % n_tasks) % 2 for c in contexts])
    seen: dict[int, int] = {}
    out = []
    for c in contexts:
        t = int(c) % n_tasks
        out.append(seen.get(t, 0) % 2)
        seen[t] = seen.get(t, 0) + 1
    return torch.tensor(out)


def half_agreement(entries: list[dict], discount: float = 1.0, judged_by: float | None = None, n_tasks: int = 1,
                   across_tasks: bool = False) -> dict:
    """Does a direction's measured effect repeat on other starts? Each ledger entry's pair differences
    R(+k) - R(-k) on one half of its contexts against those on the other (`halves`: each task's starts split
    between them; `n_tasks`, the suite's task count, says which task a context number is): their cosine per
    iteration and pooled over the entries (about 0 where the pairs' differences are the starts' noise, toward 1
    where the weight-space directions carry a signal), the counterpart of PPO's even/odd gradient cosine.
    `across_tasks`: one half of the tasks against the other instead: whether a direction that helps some tasks
    helps the others (about 0 or below where a step chosen on some tasks is a random move for the rest).
    `judged_by`: the other half's returns under this discount instead (both ways round): whether differences
    measured with a shaped return (`discount` < 1, a faster success worth more) point where the benchmark's
    success (`judged_by=1`) does on starts they were not measured on."""
    if across_tasks and n_tasks < 2:
        raise ValueError("an agreement across tasks needs n_tasks >= 2")
    ways = [(0, 1)] if judged_by is None else [(0, 1), (1, 0)]
    judge = discount if judged_by is None else judged_by
    per, dots, sq_a, sq_b = [], 0.0, 0.0, 0.0
    for e in entries:
        success, steps = torch.tensor(e["success"]), torch.tensor(e["steps"])
        half = halves(e.get("contexts", range(len(success))), n_tasks, across_tasks)
        if half.min() == half.max():  # one context, or one task where halves of tasks were asked for
            per.append(float("nan"))
            continue
        dot = a = b = 0.0
        for h, other in ways:
            r_a = member_returns(success[half == h], steps[half == h], discount).view(-1, 2)
            r_b = member_returns(success[half == other], steps[half == other], judge).view(-1, 2)
            d_a, d_b = r_a[:, 0] - r_a[:, 1], r_b[:, 0] - r_b[:, 1]
            dot, a, b = dot + float(d_a @ d_b), a + float(d_a @ d_a), b + float(d_b @ d_b)
        per.append(dot / (a * b) ** 0.5 if a * b > 0 else float("nan"))
        dots, sq_a, sq_b = dots + dot, sq_a + a, sq_b + b
    pooled = dots / (sq_a * sq_b) ** 0.5 if sq_a * sq_b > 0 else float("nan")
    return {"per_iteration": per, "pooled": pooled, "iterations": len(entries)}


@torch.no_grad()
def imagined_member_outcomes(policy: torch.nn.Module, env, contexts: list, members: list[tuple[int, float]],
                             encoder, which: str = "mean") -> dict:
    """Every member (`antithetic_members`: `policy` moved by (seed, coef)) from every context in the imagined
    environment (`ImaginedEnv`: the world simulator, the reflector's verdict as the reward), with its mean
    actions. All members x contexts rollouts advance together through the world model, a chunk at a time;
    each member's policy reads only its own rows. -> success (the verdict), steps and reward (the reflector's R where
    the rollout ended: a graded verdict where none crossed eta), (contexts, members)."""
    import copy
    import time

    t0 = time.perf_counter()
    built = [perturb(copy.deepcopy(policy).eval(), seed, coef, which) for seed, coef in members]
    n = len(contexts)
    state = env.reset([c for _ in members for c in contexts])  # member-major: member m owns rows m*n..(m+1)*n-1
    lang = encoder([c.instruction for _ in members for c in contexts]).to(state.frames.device)
    camera, t_policy = policy.cameras[0], 0.0
    while not state.done.all():
        t1 = time.perf_counter()
        mu = torch.cat([member({camera: state.frames[m * n:(m + 1) * n]}, state.proprio[m * n:(m + 1) * n],
                               lang[m * n:(m + 1) * n])[0] for m, member in enumerate(built)])
        t_policy += time.perf_counter() - t1
        state = env.step(policy.unnormalize_actions(mu))
    shape = (len(members), n)
    total = time.perf_counter() - t0
    return {"success": state.by_reflector.cpu().view(shape).T, "steps": state.t.cpu().view(shape).T,
            "reward": state.reward.float().cpu().view(shape).T,
            "episodes": 0, "errors": 0,  # imagined: no real episode
            "timing": {"policy": t_policy, "imagination": total - t_policy}}
