import numpy as np
import pytest

from worldenv_core.envs.tasks import SUITES, UnknownTaskError, get_task, init_states, num_tasks, resolve_task_ids


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
