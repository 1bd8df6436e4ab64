"""LOOP's contexts from fresh placements and the recipes as config groups (no simulator)."""
import torch
from omegaconf import OmegaConf

from stages.post_train_loop.training import placements, rl_phase
from worldenv_core.stage import compose_config


def test_fresh_placement_contexts_cycle_the_tasks_and_never_repeat(contract):
    start = placements(contract(task_ids=(0, 2), suite="libero_spatial"))
    starts = [start(k) for k in range(6)]
    assert [s.task_id for s, _ in starts] == [0, 2] * 3
    assert len({s.seed for s, _ in starts}) == 6 and start(4) == starts[4]  # numbered: the same context every time
    assert starts[0][1] != starts[1][1] and all(s.placement for s, _ in starts)  # each task's own instruction


def test_each_iteration_draws_a_run_of_new_context_numbers():
    """n_contexts None (fresh placements): an iteration's contexts are consecutive numbers from
    a start its seed draws, so they spread over the tasks and differ from other iterations'."""
    seen = []

    def collect(behaviour, picks, gens):
        seen.append(picks)
        raise StopIteration  # the picks are all this test needs
    rl = OmegaConf.create({"iterations": 3, "contexts_per_iteration": 4, "n_rollouts": 2})
    phase = rl_phase(torch.nn.Linear(1, 1), None, collect, None, rl, seed=0)
    for it in range(3):
        try:
            phase.step(torch.Generator().manual_seed(it))
        except StopIteration:
            pass
    assert all(p == list(range(p[0], p[0] + 4)) for p in seen) and len({p[0] for p in seen}) == 3


def test_the_recipes_are_a_config_group_with_the_papers_as_default():
    paper = compose_config("post_train_loop", ["+task=libero_spatial"]).rl
    tuned = compose_config("post_train_loop", ["+task=libero_spatial", "env=real", "rl=trust_region"]).rl
    assert (paper.contexts_per_iteration, paper.n_rollouts, paper.ppo_epochs, paper.lr_heads) == (4, 8, 2, 1e-5)
    assert paper.contexts == "episodes" and paper.max_kl is None and paper.group_success is None
    assert tuned.contexts == "placements" and tuned.max_kl > 0 and list(tuned.group_success) == [0.1, 0.9]
    assert tuned.contexts_per_iteration * tuned.n_rollouts >= 4 * paper.contexts_per_iteration * paper.n_rollouts
    assert set(paper) == set(tuned)  # one schema: a recipe sets values, it adds no setting of its own
