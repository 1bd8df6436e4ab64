"""A critic for LOOP: per-chunk advantages instead of one verdict spread over every chunk.

RLOO gives a rollout one advantage, its reward less the mean of the others from the same start,
and PPO applies it to each of the rollout's ~27 chunks alike: the chunks that decided the outcome
and the ones that did not get the same credit, so the policy gradient's noise grows with the
rollout's length (measured on libero_spatial: a pooled signal of 0.24 against a noise of 185 per
mixed group). A value V(s) = P(success | the state a chunk starts from), learned from earlier
rollouts, turns the one verdict into credit per chunk: generalised advantage estimation with
gamma 1 on the terminal reward, delta_t = V(s_{t+1}) - V(s_t) and, at a rollout's last chunk,
R - V(s_t); A_t = sum_k lambda^k delta_{t+k}. lambda = 1 gives R - V(s_t), unbiased whatever V
is (a state-dependent baseline); lambda < 1 concentrates the credit where the value moved, at a
bias where V is wrong. The critic reads the policy's own features of the chunk's observation,
detached (it never moves the policy), and how deep into the horizon the chunk is.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from worldenv_core.models.policy import mlp


class ChunkCritic(nn.Module):
    """logit P(success) from a chunk's policy features (B, F) and its depth: chunk index over the
    horizon's chunks, in [0, 1] (the same state is worth less with less time left)."""

    def __init__(self, feature_dim: int, horizon_chunks: int, hidden: int = 256):
        super().__init__()
        if horizon_chunks < 1:
            raise ValueError(f"the critic needs a horizon of at least one chunk, got {horizon_chunks}")
        self.feature_dim, self.horizon_chunks, self.hidden = int(feature_dim), int(horizon_chunks), int(hidden)
        self.net = mlp(self.feature_dim + 1, self.hidden, 1, layers=2)

    def forward(self, features: torch.Tensor, chunk_index: torch.Tensor) -> torch.Tensor:
        depth = chunk_index.float()[:, None] / self.horizon_chunks
        return self.net(torch.cat([features, depth], dim=-1)).squeeze(-1)


@torch.no_grad()
def chunk_features(policy, batch, block: int = 256) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The policy's features of every chunk a rollout really took: (n, F) with their rollout and
    chunk indices (rr, cc), in blocks of `block` observations (memory stays bounded)."""
    live = batch.mask[:, :, 0] > 0
    rr, cc = live.nonzero(as_tuple=True)
    camera = policy.cameras[0]
    policy.eval()
    feats = [policy.features({camera: batch.frames[rr[i:i + block], cc[i:i + block]]}, batch.proprio[rr[i:i + block], cc[i:i + block]],
                             batch.instruction[rr[i:i + block]]) for i in range(0, len(rr), block)]
    return (torch.cat(feats) if feats else torch.zeros(0, 0)), rr, cc


@torch.no_grad()
def chunk_values(critic: ChunkCritic, feats: torch.Tensor, rr: torch.Tensor, cc: torch.Tensor,
                 shape: tuple[int, int]) -> torch.Tensor:
    """V (R, C) in [0, 1] at the live chunks (0 elsewhere)."""
    values = torch.zeros(shape, device=feats.device)
    if len(rr):
        values[rr, cc] = torch.sigmoid(critic(feats, cc))
    return values


def gae_advantages(values: torch.Tensor, live: torch.Tensor, rewards: torch.Tensor, lam: float) -> torch.Tensor:
    """Per-chunk advantages (R, C) with gamma 1 and the reward at the end: values and live (R, C)
    (live chunks are a prefix of each row), rewards (R,). Zero at chunks not taken."""
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"GAE's lambda must be in [0, 1], got {lam}")
    live = live.bool()
    last = live & ~torch.cat([live[:, 1:], torch.zeros_like(live[:, :1])], dim=1)  # each row's last live chunk
    following = torch.cat([values[:, 1:], torch.zeros_like(values[:, :1])], dim=1)
    target = torch.where(last, rewards[:, None].expand_as(values), following)
    delta = torch.where(live, target - values, torch.zeros_like(values))
    adv = torch.zeros_like(values)
    carry = torch.zeros_like(rewards, dtype=values.dtype)
    for t in range(values.shape[1] - 1, -1, -1):
        carry = delta[:, t] + lam * carry * live[:, t].float()
        adv[:, t] = carry
    return adv * live.float()


def fit_critic(critic: ChunkCritic, optimizer: torch.optim.Optimizer, feats: torch.Tensor, cc: torch.Tensor,
               targets: torch.Tensor, steps: int, minibatch: int, generator: torch.Generator | None = None) -> dict:
    """`steps` Adam steps of binary cross-entropy between V at each chunk and its rollout's
    eventual reward (the Monte-Carlo target of gamma 1), minibatches drawn with replacement."""
    if steps < 0 or minibatch < 1:
        raise ValueError(f"fit_critic needs steps >= 0 and minibatch >= 1, got {steps} and {minibatch}")
    critic.train()
    losses = []
    for _ in range(steps if len(cc) else 0):
        idx = torch.randint(len(cc), (min(minibatch, len(cc)),), generator=generator).to(cc.device)
        loss = F.binary_cross_entropy_with_logits(critic(feats[idx], cc[idx]), targets[idx])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    critic.eval()
    return {"critic_loss_first": losses[0] if losses else float("nan"),
            "critic_loss_last": sum(losses[-10:]) / len(losses[-10:]) if losses else float("nan")}


@torch.no_grad()
def critic_bce(critic: ChunkCritic, feats: torch.Tensor, cc: torch.Tensor, targets: torch.Tensor) -> float:
    """Its cross-entropy on chunks it was not fitted to: below the constant predictor's (the
    success rate's entropy) only where it reads something of the state."""
    return float(F.binary_cross_entropy_with_logits(critic(feats, cc), targets)) if len(cc) else float("nan")


def constant_bce(targets: torch.Tensor) -> float:
    """The cross-entropy of always predicting the success rate: what a critic must beat."""
    rate = min(max(float(targets.mean()), 1e-6), 1 - 1e-6)
    return float(F.binary_cross_entropy(torch.full_like(targets, rate), targets))


class ChunkValue:
    """The stage's critic (`rl.advantages=gae`): each iteration's batch gets per-chunk advantages
    from what the critic learned of the batches before it (the first batch, before any fit, keeps
    RLOO's), then the critic is fitted to that batch, so no batch is judged by a critic that saw its
    outcomes. Its cross-entropy on each new batch before the fit is the measure of what it knows
    (`critic_bce` against the constant predictor's, `critic_bce_constant`). Built at its first batch
    (the width of the policy's features); `state_dict` (weights, optimizer, fits, the replay) is
    checkpointed with the policy (the Trainer's `extra_state`). `replay` = K: the fit also sees the K
    batches before (their chunks' features as the policy of their iteration computed them, in
    half precision: ~6 MB a batch of 256 rollouts), a critic from more rollouts than one batch holds."""

    def __init__(self, horizon_chunks: int, hidden: int, lr: float, steps: int, minibatch: int, lam: float,
                 replay: int = 0):
        if not 0.0 <= lam <= 1.0:
            raise ValueError(f"rl.gae_lambda must be in [0, 1], got {lam}")
        if replay < 0:
            raise ValueError(f"rl.critic_replay must be >= 0, got {replay}")
        self.horizon_chunks, self.hidden, self.lr = int(horizon_chunks), int(hidden), float(lr)
        self.steps, self.minibatch, self.lam, self.fits = int(steps), int(minibatch), float(lam), 0
        self.replay, self.kept = int(replay), []  # kept: (features fp16, chunk index, target) of recent batches
        self.critic: ChunkCritic | None = None
        self.optimizer: torch.optim.Optimizer | None = None

    def _build(self, feature_dim: int, device) -> None:
        self.critic = ChunkCritic(feature_dim, self.horizon_chunks, self.hidden).to(device)
        self.optimizer = torch.optim.Adam(self.critic.parameters(), lr=self.lr)

    def advantages(self, policy, batch, generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict]:
        """(advantages for `batch`: (R, C), or RLOO's (R,) before the first fit; diagnostics)."""
        feats, rr, cc = chunk_features(policy, batch)
        if not len(rr):
            return batch.advantages, {"critic_fits": float(self.fits)}
        if self.critic is None:
            self._build(feats.shape[1], feats.device)
        targets = batch.rewards[rr].float()
        live = batch.mask[:, :, 0] > 0
        stats = {"critic_fits": float(self.fits)}
        adv = batch.advantages
        if self.fits:
            values = chunk_values(self.critic, feats, rr, cc, tuple(live.shape))
            adv = gae_advantages(values, live, batch.rewards.float(), self.lam)
            stats.update({"critic_bce": critic_bce(self.critic, feats, cc, targets),
                          "critic_bce_constant": constant_bce(targets),
                          "advantage_abs_mean": float(adv[live].abs().mean())})
        self.kept = [*self.kept, (feats.half(), cc, targets)][-(self.replay + 1):]
        fit_feats, fit_cc, fit_targets = (torch.cat([k[i] for k in self.kept]) for i in range(3))
        stats.update(fit_critic(self.critic, self.optimizer, fit_feats.float(), fit_cc, fit_targets, self.steps,
                                self.minibatch, generator))
        stats["critic_fit_chunks"] = float(len(fit_cc))
        self.fits += 1
        return adv, stats

    def state_dict(self) -> dict:
        if self.critic is None:
            return {"fits": 0}
        return {"feature_dim": self.critic.feature_dim, "critic": self.critic.state_dict(),
                "optimizer": self.optimizer.state_dict(), "fits": self.fits, "kept": self.kept}

    def load_state_dict(self, state: dict, device="cpu") -> None:
        self.fits = int(state["fits"])
        if "critic" in state:
            self._build(int(state["feature_dim"]), device)
            self.critic.load_state_dict(state["critic"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.kept = [tuple(t.to(device) for t in k) for k in state.get("kept", [])]
