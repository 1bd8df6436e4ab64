"""LOOP (paper sec. 4.3, Algorithm 1): RLOO advantages and the clipped PPO objective of eq. 5.

Shapes: a batch holds C contexts x N rollouts. Per-step log-probabilities are over one executed
action (the sum over its action dimensions); `mask` marks the steps a rollout really took
(1..T_n), so padding after termination never counts.
"""

from __future__ import annotations

import dataclasses
import math

from dataclasses import dataclass, field

import torch


def rloo_advantages(rewards: torch.Tensor) -> torch.Tensor:
    """rewards (C, N) -> A_n = R_n - mean of the other N - 1 rewards of the same context."""
    n = rewards.shape[-1]
    if n < 2:
        raise ValueError(f"RLOO needs at least 2 rollouts per context, got N={n}")
    baseline = (rewards.sum(-1, keepdim=True) - rewards) / (n - 1)
    return rewards - baseline


def ppo_loss(logp_new: torch.Tensor, logp_old: torch.Tensor, advantages: torch.Tensor, mask: torch.Tensor,
             epsilon: float) -> tuple[torch.Tensor, dict]:
    """Eq. 5: -(1 / sum_n T_n) sum_n sum_t min(r A_n, clip(r, 1 - eps, 1 + eps) A_n).

    logp_new, logp_old, mask: (R, T) over R rollouts; advantages (R,), broadcast over each
    trajectory, or (R, C) per chunk of T / C steps (a critic's, `critic.gae_advantages`). Returns
    the loss and diagnostics (clip fraction, approximate KL, mean ratio)."""
    if not epsilon > 0:
        raise ValueError(f"PPO clip epsilon must be > 0, got {epsilon}")
    mask = mask.float()
    steps = mask.sum().clamp(min=1.0)
    log_ratio = (logp_new - logp_old) * mask
    ratio = log_ratio.exp()
    if advantages.dim() == 1:
        adv = advantages[:, None].expand_as(ratio)
    elif ratio.shape[1] % advantages.shape[1] == 0:
        adv = advantages.repeat_interleave(ratio.shape[1] // advantages.shape[1], dim=1)
    else:
        raise ValueError(f"per-chunk advantages {tuple(advantages.shape)} do not divide the steps {tuple(ratio.shape)}")
    surrogate = torch.minimum(ratio * adv, ratio.clamp(1 - epsilon, 1 + epsilon) * adv)
    loss = -(surrogate * mask).sum() / steps
    with torch.no_grad():
        clipped = ((ratio - 1).abs() > epsilon).float()
        stats = {"clip_fraction": float((clipped * mask).sum() / steps),
                 # the low-variance estimator (r - 1) - log r of KL(old || new)
                 "approx_kl": float((((ratio - 1) - log_ratio) * mask).sum() / steps),
                 "ratio_mean": float((ratio * mask).sum() / steps)}
    return loss, stats


# ---- Algorithm 1: rollouts in imagination, then K PPO steps -------------------------------------


@dataclass
class RolloutBatch:
    """Everything PPO needs from one iteration's rollouts. R rollouts x C chunks of K steps."""

    frames: torch.Tensor  # (R, C, 3, H, W) uint8: the observation each chunk was chosen from
    proprio: torch.Tensor  # (R, C, 7)
    instruction: torch.Tensor  # (R, D) instruction embeddings
    actions: torch.Tensor  # (R, C, K, A) sampled actions, in the policy's normalised space
    logp_old: torch.Tensor  # (R, C, K) behaviour log-probabilities per executed step
    mask: torch.Tensor  # (R, C, K) 1 where the rollout had not terminated before that chunk
    rewards: torch.Tensor  # (R,) R(o_{1:t_end}, g)
    advantages: torch.Tensor  # (R,) RLOO's, one per rollout; or (R, C), one per chunk (a critic's)
    t_end: torch.Tensor  # (R,) steps taken
    by_reflector: torch.Tensor  # (R,) stopped because R > eta
    beta_mean: float
    # the behaviour's Laplace parameters at every chunk (R, C, K, A): the exact KL of a trust region
    mu_old: torch.Tensor | None = None
    beta_old: torch.Tensor | None = None
    timing: dict = field(default_factory=dict)  # seconds by part (physics, render, policy, ...), summed over rollouts
    noise_scale: float = 1.0  # the actions were drawn from Laplace(mu, noise_scale * e^beta): log-probs are of that
    exploration: str = "step"  # a draw per step, or one per chunk held for its K steps (`laplace.chunk_log_prob`)


@torch.no_grad()
def collect_rollouts(policy, env, contexts: list, n_rollouts: int, encoder,
                     generator: torch.Generator | list[torch.Generator] | None = None, observer=None,
                     noise_scale: float = 1.0, exploration: str = "step") -> RolloutBatch:
    """N rollouts per context from the frozen behaviour policy (Algorithm 1, lines 5-25): actions
    ~ Laplace(mu, exp(beta)); all C x N rollouts advance together until every one is done.
    `generator`: one for the batch, or one per context, whose N rollouts then draw from it alone
    (the same rollouts whichever other contexts share the batch: sharding over ranks).
    `observer` (e.g. `ImaginedRecorder`) sees the reset state and every step: `on_reset(state)`,
    `on_step(actions, mu, beta, state)` with actions and mu in the simulator's units. `noise_scale`
    multiplies the Laplace scale (1: the policy's own; evaluating a noisier or calmer variant);
    `exploration` (`laplace.laplace_sample`): a draw per step, or one per chunk."""
    from worldenv_core.models.laplace import chunk_log_prob, laplace_sample

    if n_rollouts < 2:
        raise ValueError(f"RLOO needs at least 2 rollouts per context, got N={n_rollouts}")
    policy.eval()
    expanded = [c for c in contexts for _ in range(n_rollouts)]  # context-major: (C, N) after a view
    state = env.reset(expanded)
    if observer is not None:
        observer.on_reset(state)
    lang = encoder([c.instruction for c in expanded]).to(state.frames.device)
    camera = policy.cameras[0]
    frames, proprio, actions, logps, masks, betas, mus, betas_all = [], [], [], [], [], [], [], []
    while not state.done.all():
        mu, beta = policy({camera: state.frames}, state.proprio, lang)
        a = laplace_sample(mu, beta, generator, noise_scale, exploration)
        frames.append(state.frames), proprio.append(state.proprio), actions.append(a)
        mus.append(mu), betas_all.append(beta)
        logps.append(chunk_log_prob(a, mu, beta, noise_scale, exploration))  # (R, K): per executed step, as drawn
        masks.append((~state.done).float()[:, None].expand(-1, a.shape[1]))
        betas.append(beta[~state.done].mean())
        state = env.step(policy.unnormalize_actions(a), generator=generator)
        if observer is not None:
            observer.on_step(policy.unnormalize_actions(a), policy.unnormalize_actions(mu), beta, state)
    rewards = state.reward.float()
    advantages = rloo_advantages(rewards.view(len(contexts), n_rollouts)).reshape(-1)
    return RolloutBatch(frames=torch.stack(frames, 1), proprio=torch.stack(proprio, 1), instruction=lang,
                        actions=torch.stack(actions, 1), logp_old=torch.stack(logps, 1), mask=torch.stack(masks, 1),
                        rewards=rewards, advantages=advantages, t_end=state.t, by_reflector=state.by_reflector,
                        beta_mean=float(torch.stack(betas).mean()), mu_old=torch.stack(mus, 1),
                        beta_old=torch.stack(betas_all, 1), noise_scale=float(noise_scale), exploration=exploration)


def merge(parts: list[RolloutBatch]) -> RolloutBatch:
    """Batches of disjoint contexts (one per rank) as one, in order: chunk dimensions padded to
    the longest with mask 0 (a rank whose rollouts all ended sooner took fewer chunks)."""
    if len(parts) == 1:
        return parts[0]
    chunks = max(p.mask.shape[1] for p in parts)

    def cat(name):
        return torch.cat([_pad_chunks(getattr(p, name), chunks) for p in parts])
    n = [len(p.rewards) for p in parts]
    behaviour = all(p.mu_old is not None for p in parts)
    timing = {k: sum(p.timing.get(k, 0.0) for p in parts) for k in dict.fromkeys(k for p in parts for k in p.timing)}
    return RolloutBatch(frames=cat("frames"), proprio=cat("proprio"), instruction=torch.cat([p.instruction for p in parts]),
                        actions=cat("actions"), logp_old=cat("logp_old"), mask=cat("mask"),
                        rewards=torch.cat([p.rewards for p in parts]), advantages=torch.cat([p.advantages for p in parts]),
                        t_end=torch.cat([p.t_end for p in parts]), by_reflector=torch.cat([p.by_reflector for p in parts]),
                        beta_mean=sum(p.beta_mean * k for p, k in zip(parts, n)) / sum(n),
                        mu_old=cat("mu_old") if behaviour else None, beta_old=cat("beta_old") if behaviour else None,
                        timing=timing, noise_scale=parts[0].noise_scale,
                        exploration=parts[0].exploration)


def _pad_chunks(x: torch.Tensor, chunks: int) -> torch.Tensor:
    """(R, C, ...) -> (R, chunks, ...), the new chunks zeros (masked out; a frame never looked at)."""
    if x.shape[1] == chunks:
        return x
    return torch.cat([x, x.new_zeros((x.shape[0], chunks - x.shape[1], *x.shape[2:]))], dim=1)


def informative_groups(batch: RolloutBatch, n_rollouts: int,
                       success_range: tuple[float, float] | None = None) -> torch.Tensor:
    """(R,) bool: the rollouts of contexts whose N verdicts (success by the reward model's eta, or
    the oracle) do not all agree. Where all N agree, the advantages only spread the reward
    model's score below (or above) eta, which is noise, not a verdict: peers that gain with
    world-model RL drop such groups rather than spend PPO steps on them. `success_range`
    (lo, hi): also drop mixed groups whose success fraction lies outside [lo, hi] (SimpleVLA-RL
    and WoVR keep 10-90 %: one success in 16 is mostly the noise of that one rollout)."""
    verdicts = batch.by_reflector.view(-1, n_rollouts)
    mixed = verdicts.any(-1) & ~verdicts.all(-1)
    if success_range is not None:
        lo, hi = success_range
        fraction = verdicts.float().mean(-1)
        mixed &= (fraction >= lo - 1e-9) & (fraction <= hi + 1e-9)
    return mixed.repeat_interleave(n_rollouts)


def check_success_range(success_range) -> tuple[float, float] | None:
    """The group filter's (lo, hi) success fractions, validated; None stays None (mixed groups only)."""
    if success_range is None:
        return None
    lo, hi = (float(x) for x in success_range)
    if not 0.0 <= lo <= hi <= 1.0:
        raise ValueError(f"group success range must be two fractions 0 <= lo <= hi <= 1, got {list(success_range)}")
    return lo, hi


def permute_verdicts(batch: RolloutBatch, n_rollouts: int, generator: torch.Generator | None = None) -> RolloutBatch:
    """A control, not the method: the batch's verdicts (reward and success flag) shuffled across its
    rollouts, advantages recomputed. As many successes as the environment gave, on rollouts it did
    not give them to: a policy that gains under it gained from the update itself (its noise, its
    step), not from what the environment told it."""
    perm = torch.randperm(len(batch.rewards), generator=generator)
    rewards = batch.rewards[perm]
    return dataclasses.replace(batch, rewards=rewards, by_reflector=batch.by_reflector[perm],
                               advantages=rloo_advantages(rewards.view(-1, n_rollouts)).reshape(-1))


def select(batch: RolloutBatch, keep: torch.Tensor) -> RolloutBatch:
    """The rollouts where `keep` (R,) is true (their advantages as computed on the whole group)."""
    return dataclasses.replace(batch, **{f.name: getattr(batch, f.name)[keep] for f in dataclasses.fields(batch)
                                         if isinstance(getattr(batch, f.name), torch.Tensor)})


def ppo_update(policy, optimizer, batch: RolloutBatch, epochs: int, epsilon: float, minibatch: int,
               generator: torch.Generator | None = None, target_kl: float | None = None,
               max_kl: float | None = None, kl_states: int = 512, backtracks: int = 10,
               direction_groups: int | None = None) -> dict:
    """K epochs of eq. 5 over the batch's rollouts in minibatches of whole rollouts; the loss of
    each minibatch is normalised by its summed trajectory lengths. `target_kl`: the iteration's
    remaining steps are skipped once a minibatch's approximate KL from the behaviour policy
    exceeds 1.5 x target_kl, that minibatch's own step included (as Stable-Baselines3's PPO does).

    `max_kl`: a trust region in action space. The clip bounds each ratio, not how far many steps
    together take the policy, and Adam moves every parameter by about the learning rate whatever
    the advantages' scale (measured here: one Adam step at lr 1e-4 took the policy to an
    approximate KL of 0.7-1.9). So after every step, the first included, the exact KL from the
    behaviour's Laplace to the policy's (mean per executed step, summed over action dimensions)
    is measured on up to `kl_states` fixed chunk states of the batch; a step that crosses `max_kl`
    is shrunk by halves (up to `backtracks` times, else undone) and ends the iteration.
    `direction_groups` = N: before the first step, the policy gradient of the batch's even groups
    of N rollouts against its odd ones (`direction_cosine`): about 0 when the batch is too small for
    its direction to be the reward's, towards 1 as it grows (with a signal s and per-group noise,
    cos ~ B|s|^2 / (B|s|^2 + 2 sigma^2) over B groups, so it says how many groups would do).
    `ppo_steps` counts the steps taken."""
    if target_kl is not None and not target_kl > 0:  # as ppo_loss checks epsilon: a caller outside the stage reaches here unvalidated
        raise ValueError(f"target_kl must be > 0 or None (no limit), got {target_kl}")
    if max_kl is not None and not max_kl > 0:
        raise ValueError(f"max_kl must be > 0 or None (no trust region), got {max_kl}")
    if max_kl is not None and batch.mu_old is None:
        raise ValueError("max_kl needs the behaviour's Laplace parameters in the batch (mu_old, beta_old)")
    # eval mode although it trains: the ratio compares the policy with the behaviour's eval-mode
    # log-probabilities, and a dropout mask (ACT's 0.1) would move mu by far more than a Laplace scale of
    # e^-2.5 tolerates (measured: ratio 0.0007 on the first, unchanged step); RLHF's PPO turns dropout off too
    policy.eval()
    r = batch.mask.shape[0]
    params = [p for g in optimizer.param_groups for p in g["params"]]
    stats: dict[str, list[float]] = {"loss": [], "clip_fraction": [], "approx_kl": [], "ratio_mean": []}
    steps, shrunk, first_kl, stopped = 0, 0, None, False
    order = [idx for _ in range(epochs) for idx in torch.randperm(r, generator=generator).split(minibatch)]
    probe = kl_probe(batch, kl_states, generator)  # drawn after the order: the minibatches are as before
    direction = direction_cosine(policy, batch, direction_groups, epsilon) if direction_groups else None
    for idx in order:
        loss, s = _rollouts_loss(policy, batch, idx, epsilon)
        stats["loss"].append(loss.item())
        for k, v in s.items():
            stats[k].append(v)
        if target_kl is not None and s["approx_kl"] > 1.5 * target_kl:
            break
        before = [p.detach().clone() for p in params] if max_kl is not None else None
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()
        steps += 1
        if max_kl is not None:
            kl = probe.kl(policy)
            first_kl = kl if first_kl is None else first_kl
            if kl > max_kl:
                stopped = True
                after = [p.detach().clone() for p in params]
                for k in range(1, backtracks + 1):  # shrink the step towards where it started
                    _interpolate(params, before, after, 0.5 ** k)
                    shrunk += 1
                    if (kl := probe.kl(policy)) <= max_kl:
                        break
                else:
                    _interpolate(params, before, after, 0.0)
                    steps -= 1
                break
    policy.eval()
    out = {**{k: sum(v) / len(v) for k, v in stats.items()}, "ppo_steps": steps}
    if direction is not None:
        out.update(direction)
    if probe is not None:
        out.update(probe.summary(policy))
        if max_kl is not None:
            out.update({"first_step_kl": first_kl if first_kl is not None else 0.0, "backtracks": shrunk,
                        "trust_region_hit": float(stopped)})
    return out


def _rollouts_loss(policy, batch: RolloutBatch, rows: torch.Tensor, epsilon: float) -> tuple[torch.Tensor, dict]:
    """Eq. 5 over the rollouts `rows`: the policy on the chunks they really took, log-probs of the
    distribution the actions were drawn from (`noise_scale`, `exploration`)."""
    from worldenv_core.models.laplace import chunk_log_prob

    live = batch.mask[rows, :, 0] > 0  # (m, C): chunks the rollout really took
    rr, cc = live.nonzero(as_tuple=True)
    mu, beta = policy({policy.cameras[0]: batch.frames[rows][rr, cc]}, batch.proprio[rows][rr, cc],
                      batch.instruction[rows][rr])
    logp = torch.zeros_like(batch.logp_old[rows])
    logp[rr, cc] = chunk_log_prob(batch.actions[rows][rr, cc], mu, beta, batch.noise_scale, batch.exploration)
    return ppo_loss(logp.flatten(1), batch.logp_old[rows].flatten(1), batch.advantages[rows],
                    batch.mask[rows].flatten(1), epsilon)


def _policy_gradient(policy, batch: RolloutBatch, rows: torch.Tensor, epsilon: float) -> torch.Tensor:
    """The flattened gradient of eq. 5 over `rows` at the current parameters."""
    loss, _ = _rollouts_loss(policy, batch, rows, epsilon)
    params = [p for p in policy.parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return torch.cat([(g if g is not None else torch.zeros_like(p)).flatten() for g, p in zip(grads, params)])


def gradient_signal(sum_g: torch.Tensor, sum_sq: float, groups: int) -> dict:
    """Signal and noise of a batch's policy gradient from its groups' gradients g_i (their sum and
    the sum of their squared norms): with g_i = s + noise of variance sigma^2 (total over
    parameters), E|g_i|^2 = |s|^2 + sigma^2 and E|mean g|^2 = |s|^2 + sigma^2 / B, so
    |s|^2 = (B |mean g|^2 - mean |g_i|^2) / (B - 1). The batch's gradient points along the reward's
    with cos^2 = |s|^2 / (|s|^2 + sigma^2 / B): `groups_for_cos_0.9` is the B at which cos = 0.9
    (inf where no signal is measurable: the estimate of |s|^2 is <= 0)."""
    if groups < 2:
        raise ValueError(f"the gradient's signal needs at least 2 groups, got {groups}")
    mean_sq = float((sum_g / groups).pow(2).sum())
    signal = (groups * mean_sq - sum_sq / groups) / (groups - 1)
    noise = sum_sq / groups - signal
    snr = signal / noise if noise > 0 and signal > 0 else 0.0
    cos = math.sqrt(signal / (signal + noise / groups)) if signal > 0 else 0.0
    return {"gradient_signal_sq": signal, "gradient_noise_sq": noise, "gradient_cos_to_signal": cos,
            "groups_for_cos_0.9": (0.81 / 0.19) / snr if snr > 0 else float("inf")}


def direction_cosine(policy, batch: RolloutBatch, n: int, epsilon: float) -> dict | None:
    """How far the batch's direction is the reward's: the cosine between the policy gradients of
    its even and its odd groups of N rollouts, and the signal and noise from each group's own
    gradient (`gradient_signal`)."""
    groups = len(batch.rewards) // n
    if groups < 2:
        return None
    sum_g, sum_sq, evens, odds = None, 0.0, 0, 0
    for k in range(groups):
        g = _policy_gradient(policy, batch, torch.arange(k * n, (k + 1) * n, device=batch.rewards.device), epsilon)
        sum_g = g.clone() if sum_g is None else sum_g + g
        sum_sq += float(g.pow(2).sum())
        if k % 2:
            odds = odds + g
        else:
            evens = evens + g
    return {"direction_cosine": float(torch.nn.functional.cosine_similarity(evens, odds, dim=0)),
            **gradient_signal(sum_g, sum_sq, groups)}


def _interpolate(params, before, after, w: float) -> None:
    """params <- before + w (after - before), in place."""
    with torch.no_grad():
        for p, b, a in zip(params, before, after):
            p.copy_(b + w * (a - b))


@dataclass
class KLProbe:
    """Fixed chunk states of a batch and the behaviour's Laplace at them: how far the policy moved."""

    frames: torch.Tensor
    proprio: torch.Tensor
    instruction: torch.Tensor
    mu_old: torch.Tensor  # (P, K, A)
    beta_old: torch.Tensor
    mask: torch.Tensor  # (P, K): the steps executed
    noise_scale: float = 1.0  # the KL is of the distributions the actions were drawn from, as PPO's ratios are

    @torch.no_grad()
    def _forward(self, policy):
        was = policy.training
        policy.eval()
        mu, beta = policy({policy.cameras[0]: self.frames}, self.proprio, self.instruction)
        policy.train(was)
        return mu, beta

    def summary(self, policy) -> dict:
        """How far the policy moved: the mean exact KL(behaviour || policy) per executed step, summed
        over action dimensions, of the sampling distributions (scale `noise_scale` e^beta: a wider
        sampling lets the mean move further for the same KL), and the RMS change of the mean action
        (normalised units)."""
        from worldenv_core.models.laplace import laplace_kl

        mu, beta = self._forward(policy)
        m = self.mask[..., None].expand_as(mu)
        shift = math.log(self.noise_scale)
        per_step = laplace_kl(self.mu_old, self.beta_old + shift, mu, beta + shift).sum(-1)
        return {"exact_kl": float((per_step * self.mask).sum() / self.mask.sum().clamp(min=1)),
                "action_shift_rms": float((((mu - self.mu_old) ** 2) * m).sum().div(m.sum().clamp(min=1)).sqrt())}

    def kl(self, policy) -> float:
        return self.summary(policy)["exact_kl"]


def kl_probe(batch: RolloutBatch, n: int, generator: torch.Generator | None) -> KLProbe | None:
    """Up to `n` of the batch's live chunk states, drawn once per update."""
    if batch.mu_old is None:
        return None
    rows, cols = (batch.mask[:, :, 0] > 0).nonzero(as_tuple=True)
    if len(rows) > n:
        pick = torch.randperm(len(rows), generator=generator)[:n]
        rows, cols = rows[pick], cols[pick]
    return KLProbe(frames=batch.frames[rows, cols], proprio=batch.proprio[rows, cols],
                    instruction=batch.instruction[rows], mu_old=batch.mu_old[rows, cols].detach(),
                    beta_old=batch.beta_old[rows, cols].detach(), mask=batch.mask[rows, cols],
                    noise_scale=batch.noise_scale)


def policy_param_groups(policy, lr_backbone: float, lr_heads: float, scale_head: bool = True) -> list[dict]:
    """The paper's two learning rates: the vision backbone (or its LoRA adapters) and the rest
    (trunk, action and scale heads), trainable parameters only. A learning rate of 0 leaves its
    group out: RL then trains the other alone (e.g. `rl.lr_backbone=0`, the heads only).
    `scale_head=False` keeps the Laplace scale where SFT's second phase put it: RL's gradient on
    it is the noise of |a - mu| / b - 1, and a trust region spent on the scale moves no action."""
    if lr_backbone < 0 or lr_heads < 0 or not (lr_backbone > 0 or lr_heads > 0):
        raise ValueError(f"learning rates must be >= 0 and one of them > 0, got backbone {lr_backbone}, heads {lr_heads}")
    backbone = [p for p in policy.backbone.parameters() if p.requires_grad]
    ids = {id(p) for p in backbone}
    if not scale_head:
        ids |= {id(p) for p in policy.scale_head.parameters()}
    rest = [p for p in policy.parameters() if p.requires_grad and id(p) not in ids]
    groups = [{"params": backbone, "lr": lr_backbone, "name": "backbone"}, {"params": rest, "lr": lr_heads, "name": "heads"}]
    return [g for g in groups if g["lr"] > 0 and g["params"]]


OPTIMIZERS = ("adam", "sgd")


def make_optimizer(policy, name: str, lr_backbone: float, lr_heads: float, scale_head: bool = True) -> torch.optim.Optimizer:
    """LOOP's optimiser over `policy_param_groups`: Adam (the paper's) or plain SGD, whose step is
    proportional to the gradient, so the advantages' scale sets the step as Adam's normalisation does not."""
    groups = policy_param_groups(policy, lr_backbone, lr_heads, scale_head)
    if name == "adam":
        return torch.optim.Adam(groups)
    if name == "sgd":
        return torch.optim.SGD(groups, lr=groups[0]["lr"])
    raise ValueError(f"rl.optimizer must be one of {list(OPTIMIZERS)}, got {name!r}")
