"""LOOP's contexts from fresh placements and the recipes as config groups (no simulator)."""
import collections

import pytest
import torch
from omegaconf import OmegaConf

from stages.post_train_loop.training import draw_contexts, focus_positions, placements, rl_phase
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


def test_the_every_task_recipe_gives_each_member_8_placements_of_every_task():
    rl = compose_config("post_train_loop", ["+task=libero_spatial", "env=real", "rl=es_every_task"]).rl
    assert rl.policy_update == "es" and rl.contexts == "placements" and rl.task_focus is None
    picks = draw_contexts(torch.Generator().manual_seed(0), None, rl.contexts_per_iteration,
                          focus_positions(0, rl.task_focus, 10))
    assert sorted(collections.Counter(k % 10 for k in picks).values()) == [8] * 10  # placement k is task k % 10


def test_the_many_pairs_recipe_spends_es_by_tasks_episodes_on_four_times_the_directions():
    by_task, many = (compose_config("post_train_loop", ["+task=libero_spatial", "env=real", f"rl={r}"]).rl
                     for r in ("es_by_task", "es_many_pairs"))
    assert many.es_pairs == 4 * by_task.es_pairs and many.task_focus == by_task.task_focus == 1
    assert 2 * many.es_pairs * many.contexts_per_iteration == 2 * by_task.es_pairs * by_task.contexts_per_iteration == 256
    picks = draw_contexts(torch.Generator().manual_seed(0), None, many.contexts_per_iteration,
                          focus_positions(3, many.task_focus, 10))
    assert {k % 10 for k in picks} == {3} and len(set(picks)) == 4  # 4 distinct placements of iteration 3's task


def test_the_guard_undoes_an_update_whose_hack_rate_is_above_its_bound():
    """An update the guard measures above `rl.guard_max_hack_rate` is undone: weights and Adam's state
    as before it; at or below the bound, or with no imagined success to judge (NaN), it stays."""
    from stages.post_train_loop.training import imagined_collector
    from tests.worldenv_core.rl.test_loop import ActionRewardEnv, _policy_and_contexts
    from worldenv_core.rl.loop import policy_param_groups

    rl = OmegaConf.create({"iterations": 1, "contexts_per_iteration": 2, "n_rollouts": 8, "verdicts": "own",
                           "filter_groups": False, "ppo_epochs": 2, "epsilon": 0.2, "minibatch": 8, "target_kl": None,
                           "guard_max_hack_rate": 0.5})
    for hack_rate, undone in ((1.0, True), (0.5, False), (float("nan"), False)):
        policy, contexts, encoder = _policy_and_contexts()
        optimizer = torch.optim.Adam(policy_param_groups(policy, 1e-3, 1e-3))
        start = [p.detach().clone() for p in policy.parameters()]
        measured = []

        def guard(p):
            measured.append(not all(torch.equal(a, b) for a, b in zip(p.parameters(), start)))  # after the update
            return {"guard_hack_rate": hack_rate, "guard_episodes": 4}
        phase = rl_phase(policy, optimizer, imagined_collector(ActionRewardEnv(), contexts, 8, encoder), 2, rl, 0, guard)
        stats = phase.step(torch.Generator().manual_seed(0))
        same = all(torch.equal(a, b) for a, b in zip(policy.parameters(), start))
        assert measured == [True] and stats["ppo_steps"] > 0 and stats["guard_episodes"] == 4
        assert same == undone and stats.get("rolled_back", 0.0) == float(undone)
        assert (len(optimizer.state) == 0) == undone  # Adam's moments of the undone steps are gone too


def test_a_placement_pool_draws_the_same_fixed_placements_every_iteration():
    """n_contexts = P (`rl.placement_pool`): every iteration's context numbers lie in 0..P-1, so the same P
    fresh placements recur across iterations (each start revisited), unlike the runs of new numbers above."""
    seen = []

    def collect(behaviour, picks, gens):
        seen.append(picks)
        raise StopIteration
    rl = OmegaConf.create({"iterations": 4, "contexts_per_iteration": 6, "n_rollouts": 2})
    phase = rl_phase(torch.nn.Linear(1, 1), None, collect, 5, rl, seed=0)
    for it in range(4):
        try:
            phase.step(torch.Generator().manual_seed(it))
        except StopIteration:
            pass
    drawn = {k for p in seen for k in p}
    assert drawn <= set(range(5)) and len(drawn) >= 4 and all(len(p) == 6 for p in seen)


def test_a_task_focus_draws_each_iteration_from_the_next_tasks_in_turn(contract):
    """rl.task_focus: iteration i's fresh placements are of task positions i*m .. i*m+m-1 (mod the task
    count), distinct numbers, so a cycle visits each task once and no placement repeats."""
    from stages.post_train_loop.training import draw_contexts, focus_positions

    start = placements(contract(task_ids=(0, 2, 5), suite="libero_spatial"))
    assert focus_positions(4, None, 3) is None
    assert [focus_positions(i, 1, 3)[0] for i in range(4)] == [[0], [1], [2], [0]]
    assert focus_positions(1, 2, 3) == ([2, 0], 3)
    for it, tasks in ((0, [0]), (1, [2]), (2, [5])):
        picks = draw_contexts(torch.Generator().manual_seed(it), None, 6, focus_positions(it, 1, 3))
        assert [start(k)[0].task_id for k in picks] == tasks * 6 and len(set(picks)) == 6
    picks = draw_contexts(torch.Generator().manual_seed(7), None, 4, focus_positions(1, 2, 3))
    assert [start(k)[0].task_id for k in picks] == [5, 0, 5, 0] and len(set(picks)) == 4
    with pytest.raises(ValueError, match="each context's task position"):
        draw_contexts(torch.Generator(), 10, 4, ([0], 3))


def test_a_task_focus_over_listed_contexts_takes_each_tasks_own_in_turn_without_repeats():
    """Keyframes of collected episodes (listed contexts): iteration i's contexts are of the focused tasks, in
    turn, each task's distinct until it has none left, and the same draw for the same generator."""
    from stages.post_train_loop.training import draw_contexts

    tasks = [0, 1, 2, 0, 1, 0, 2, 0]  # the task position of each listed context
    picks = draw_contexts(torch.Generator().manual_seed(3), 8, 4, ([0], 3), tasks)
    assert sorted(picks) == [0, 3, 5, 7]  # task 0's four contexts, each once
    picks = draw_contexts(torch.Generator().manual_seed(3), 8, 6, ([1, 2], 3), tasks)
    assert [tasks[k] for k in picks] == [1, 2] * 3 and sorted(picks[0::2][:2]) == [1, 4] and len(set(picks[1::2][:2])) == 2
    assert picks == draw_contexts(torch.Generator().manual_seed(3), 8, 6, ([1, 2], 3), tasks)
    with pytest.raises(ValueError, match=r"no context of the task\(s\) at position\(s\) \[1\]"):
        draw_contexts(torch.Generator(), 3, 2, ([1], 2), [0, 0, 0])
