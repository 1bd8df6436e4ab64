"""The cost model (benchmarks/training_cost.py): every training stage's step is built from its
composed config and timed; a child process per measurement reports its own peak memory."""
import pytest

from benchmarks.training_cost import STAGES, _measure, measure, table


@pytest.mark.parametrize("stage", STAGES)
def test_every_stage_step_is_timed_from_its_config(stage):
    row = _measure(stage, "tiny", "tiny", repeats=1, threads=1)
    assert row["s_per_step"] > 0 and row["steps"] > 0 and row["peak_rss_GB"] > 0
    if stage == "post_train_loop":
        assert row["imagined_env_steps_per_s"] > 0 and 0 < row["s_ppo_per_iteration"] < row["s_per_step"]


def test_a_measurement_runs_in_its_own_process_and_fills_the_table():
    row = {"stage": "train_reflector", "scale": "tiny", **measure("train_reflector", "tiny", "tiny", 1, 1)}
    assert row["hours"] == pytest.approx(row["s_per_step"] * row["steps"] / 3600)
    assert "| train_reflector | tiny |" in table([row])
