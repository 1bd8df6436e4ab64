"""Success-filtered behaviour cloning: the buffer keeps exactly the successes' chunks, survives a
resume without duplicates, and the update learns a reward on a tiny policy."""
import dataclasses

import torch
from omegaconf import OmegaConf

from tests.worldenv_core.rl.test_loop import ActionRewardEnv, _policy_and_contexts
from worldenv_core.rl.filtered_bc import SuccessBuffer, bc_update
from worldenv_core.rl.loop import collect_rollouts, policy_param_groups


class VerdictEnv(ActionRewardEnv):
    """ActionRewardEnv with a verdict: a rollout succeeds when over 30 % of its x-actions were > 0
    (about a third of the tiny policy's rollouts at three times its Laplace scale)."""

    def step(self, actions, generator=None):
        state = super().step(actions, generator)
        self.state = dataclasses.replace(state, by_reflector=state.done & (state.reward > 0.3))
        return self.state


def _batch(seed: int = 0):
    policy, contexts, encoder = _policy_and_contexts()
    batch = collect_rollouts(policy, VerdictEnv(), contexts, 8, encoder, torch.Generator().manual_seed(seed))
    return policy, contexts, encoder, batch


def test_the_buffer_keeps_the_successes_live_chunks_and_a_resume_reads_them_back(tmp_path):
    _, _, _, batch = _batch()
    batch.mask[0, 1] = 0  # rollout 0 stopped after its first chunk
    batch.by_reflector[:] = False
    batch.by_reflector[[0, 3]] = True
    buffer = SuccessBuffer(tmp_path / "buf")
    assert buffer.add("a", batch) == 2
    assert (buffer.rollouts, len(buffer)) == (2, 3)  # rollout 0's one live chunk, rollout 3's two
    data = buffer.tensors()
    assert torch.equal(data["frames"][0], batch.frames[0, 0]) and torch.equal(data["actions"][1:], batch.actions[3])
    assert data["frames"].dtype == torch.uint8 and data["instruction"].shape == (3, batch.instruction.shape[1])
    buffer.add("a", batch)  # the same iteration again (a resume): replaced, not added twice
    assert len(buffer) == 3
    again = SuccessBuffer(tmp_path / "buf")  # what a resumed run reads
    assert all(torch.equal(again.tensors()[k], data[k]) for k in data) and again.rollouts == 2
    assert not list((tmp_path / "buf").glob(".*tmp"))  # written whole, then renamed
    again.remove("a")
    assert len(again) == 0 and not list((tmp_path / "buf").glob("*.pt"))


def test_bc_update_fits_the_mean_to_the_buffer_and_leaves_the_scale_head():
    policy, _, _, batch = _batch()
    batch.by_reflector[:] = True
    batch.actions += 0.5  # successes that acted well away from the mean (the sampling noise alone is e^beta)
    buffer = SuccessBuffer(None)
    buffer.add("a", batch)
    optimizer = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-3, scale_head=False))
    scale = [p.detach().clone() for p in policy.scale_head.parameters()]
    stats = bc_update(policy, optimizer, buffer, steps=60, minibatch=8, generator=torch.Generator().manual_seed(0))
    assert stats["bc_steps"] == 60 and stats["buffer_chunks"] == len(buffer)
    assert stats["bc_loss"] < 0.5 * stats["bc_loss_first"]
    assert all(torch.equal(a, b) for a, b in zip(scale, policy.scale_head.parameters()))
    assert bc_update(policy, optimizer, SuccessBuffer(None), 5, 8)["bc_steps"] == 0  # nothing to imitate yet


def test_filtered_bc_iterations_learn_the_verdict():
    """LOOP's phase with rl.policy_update=filtered_bc: the successes' share rises well above where it began."""
    from stages.post_train_loop.training import imagined_collector, rl_phase

    policy, contexts, encoder = _policy_and_contexts(4)
    rl = OmegaConf.create({"iterations": 4, "contexts_per_iteration": 4, "n_rollouts": 8, "verdicts": "own",
                           "filter_groups": False, "policy_update": "filtered_bc", "bc_steps": 40, "bc_minibatch": 16,
                           "bc_augment_shift": 0})
    optimizer = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-3, scale_head=False))
    buffer = SuccessBuffer(None)
    phase = rl_phase(policy, optimizer, imagined_collector(VerdictEnv(), contexts, 8, encoder, noise_scale=3.0), 4, rl, 0,
                     buffer=buffer)
    rates = [phase.step(torch.Generator().manual_seed(it))["reflector_success_rate"] for it in range(4)]
    assert min(rates[2:]) > rates[0] + 0.2, rates  # measured: 0.47 -> 0.56 -> 0.72 -> 0.78
    assert buffer.rollouts == round(sum(rates) * 32)  # every success of every iteration, once
