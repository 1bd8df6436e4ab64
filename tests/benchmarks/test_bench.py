"""`make bench --only policy`: each policy config's cost per chunk, built as train_policy builds it; `--only
robot_layer`: the robot layer's cost per rollout and chunk beside a real chunk."""
import pytest

from benchmarks.bench import policy_costs, policy_episode_cost, robot_layer_cost
from tests.conftest import TINY_SUITE, TINY_TASK


def test_policy_costs_time_each_configs_chunk_and_count_its_parameters():
    out = policy_costs(["small", "lerobot_act"], "libero_object", 32, repeats=2)
    assert set(out) == {"small", "lerobot_act"}
    for row in out.values():
        assert row["ms_per_chunk"] > 0 and row["chunk"] == 8 and row["parameters_m"] > 0.1
    assert out["lerobot_act"]["parameters_m"] > out["small"]["parameters_m"]  # ACT's ResNet-18 and transformer


@pytest.mark.sim
def test_robot_layer_cost_times_the_layer_per_rollout_beside_a_real_chunk():
    out = robot_layer_cost(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=1, batch=2)
    assert out["chunk"] == 8 and out["batch"] == 2
    assert out["robot_layer_ms_per_rollout_chunk"] > 0 and out["real_chunk_ms"] > 0
    ratio = out["robot_layer_ms_per_rollout_chunk"] / out["real_chunk_ms"]
    assert abs(out["robot_layer_over_real_chunk"] - ratio) < 0.01 + 0.01 * ratio


@pytest.mark.sim
def test_policy_episode_cost_times_the_recording_with_and_without_the_kept_boundary_frames():
    out = policy_episode_cost(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=2, steps=16)
    assert out["episodes"] == 2 and out["frames_median"] == 17
    assert out["episode_s_boundaries_kept"] > 0 and out["episode_s_boundaries_replayed"] > 0
    assert 0 < out["kept_over_replayed"] < 2
