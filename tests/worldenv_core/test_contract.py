"""The task contract: built from a task config, recorded in checkpoints, checked on load."""
import pytest

from worldenv_core.contract import ContractError, TaskContract
from worldenv_core.envs.tasks import suite_max_steps
from worldenv_core.stage import compose_config, require_task


def test_built_once_from_the_task_config_with_the_derived_step_limit():
    cfg = compose_config("evaluate", ["+task=suite", "task.suite=libero_goal_swap"])
    contract = TaskContract.from_config(require_task(cfg))
    assert contract.suite == "libero_goal_swap" and contract.max_steps == 300 and contract.task_ids is None
    assert contract.cameras == ("agentview",) and contract.action_dim == 7
    assert contract.meta() == {"task": "libero_goal_swap", "suite": "libero_goal_swap", "image_size": contract.image_size,
                               "chunk": 8, "action_dim": 7, "proprio_dim": 7}
    moved = contract.on_suite("libero_goal", suite_max_steps("libero_goal"))
    assert moved.suite == "libero_goal" and moved.max_steps == 300 and moved.image_size == contract.image_size


def test_check_names_the_shape_that_differs_and_ignores_what_a_checkpoint_does_not_record(contract):
    c = contract()
    c.check({"image_size": 64, "chunk": 8, "task": "other", "suite": "libero_goal"}, "ckpt")  # suite may differ
    c.check({}, "ckpt")
    with pytest.raises(ContractError, match="ckpt was made for chunk=4, but this run's task contract .tiny. has chunk=8"):
        c.check({"chunk": 4}, "ckpt")
    with pytest.raises(ContractError, match="looks through cameras"):
        c.check({"cameras": ["robot0_eye_in_hand"]}, "ckpt")
    c.check({"cameras": {"0": {}}}, "ckpt")  # a world model's per-task camera models are not a camera list
