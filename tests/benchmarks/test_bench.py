"""`make bench --only policy`: each policy config's cost per chunk, built as train_policy builds it."""
from benchmarks.bench import policy_costs


def test_policy_costs_time_each_configs_chunk_and_count_its_parameters():
    out = policy_costs(["small", "lerobot_act"], "libero_object", 32, repeats=2)
    assert set(out) == {"small", "lerobot_act"}
    for row in out.values():
        assert row["ms_per_chunk"] > 0 and row["chunk"] == 8 and row["parameters_m"] > 0.1
    assert out["lerobot_act"]["parameters_m"] > out["small"]["parameters_m"]  # ACT's ResNet-18 and transformer
