import numpy as np
import pytest

from worldenv_core.envs.tasks import (SUITES, UnknownTaskError, base_suite, check_suite, get_task, init_states, num_tasks,
                                     registered_suites, resolve_task_ids, suite_max_steps, suite_seed_id)


@pytest.mark.parametrize("suite", SUITES)
def test_every_suite_has_ten_tasks_with_fifty_init_states(suite):
    assert num_tasks(suite) == 10
    task = get_task(suite, 9)
    assert task.instruction and task.bddl_path.endswith(".bddl")
    states = init_states(suite, 9)
    assert states.shape[0] == 50 and np.all(np.isfinite(states))


def test_unknown_suite_lists_the_valid_ones():
    with pytest.raises(UnknownTaskError, match="libero_goal"):
        get_task("libero_nope", 0)


def test_task_id_out_of_range_names_the_range():
    with pytest.raises(UnknownTaskError, match=r"0\.\.9"):
        get_task("libero_goal", 10)
    with pytest.raises(UnknownTaskError):
        resolve_task_ids("libero_goal", [0, 12])
    assert resolve_task_ids("libero_goal", None) == list(range(10))


def test_every_suite_the_benchmark_registers_is_accepted_and_the_unknown_lists_them():
    suites = registered_suites()
    assert set(SUITES) <= set(suites) and "libero_goal_swap" in suites and "libero_90" in suites
    assert len(suites) > len(SUITES)
    with pytest.raises(UnknownTaskError, match="libero_goal_swap") as e:
        check_suite("libero_nope")
    assert all(s in str(e.value) for s in suites)


@pytest.mark.parametrize("suite, base, steps", [
    ("libero_goal", "libero_goal", 300), ("libero_goal_swap", "libero_goal", 300),
    ("libero_10_lan", "libero_10", 520), ("libero_spatial_with_mug", "libero_spatial", 220),
    ("libero_90", "libero_90", 400), ("libero_100", None, None), ("libero_mine", None, None),
])
def test_a_variant_takes_the_step_limit_of_the_suite_it_derives_from(suite, base, steps):
    assert base_suite(suite) == base
    if steps is None:
        with pytest.raises(UnknownTaskError, match="task.max_steps"):
            suite_max_steps(suite)
    else:
        assert suite_max_steps(suite) == steps
    assert suite_max_steps(suite, override=123) == 123


def test_a_registered_variant_has_the_tasks_and_init_states_of_a_suite():
    task = get_task("libero_goal_swap", 3)
    assert task.suite == "libero_goal_swap" and task.bddl_path.endswith(".bddl") and task.max_steps == 300
    assert init_states("libero_goal_swap", 3).shape[0] == 50


def test_seeds_of_the_paper_suites_are_unchanged_and_others_are_stable():
    assert [suite_seed_id(s) for s in SUITES] == [0, 1, 2, 3]
    assert suite_seed_id("libero_goal_swap") == suite_seed_id("libero_goal_swap") > 3
    assert suite_seed_id("libero_goal_swap") != suite_seed_id("libero_goal_lan")
