"""Fresh placements: seeded, spread over the tasks, never a benchmark init state."""
import numpy as np
import pytest

from worldenv_core.envs.placements import BenchmarkOverlap, benchmark_distance, check_not_benchmark, placement_seed
from worldenv_core.envs.replay import placement_starts


def test_placements_are_seeded_spread_over_tasks_and_apart_by_purpose():
    starts = placement_starts("libero_spatial", [0, 3, 7], 9, "train")
    assert [s.task_id for s in starts] == [0, 3, 7] * 3 and all(s.placement for s in starts)
    assert starts == placement_starts("libero_spatial", [0, 3, 7], 9, "train")  # the same on every call and machine
    assert placement_starts("libero_spatial", [0, 3, 7], 6, "train", first=3) == starts[3:]  # numbered, not drawn
    seeds = {s.seed for s in starts}
    validation = {s.seed for s in placement_starts("libero_spatial", [0, 3, 7], 9, "validation")}
    assert len(seeds) == 9 and not seeds & validation  # training contexts are never the validation set's
    assert len({s.key for s in starts}) == 9 and starts[0].key == f"task0/placement{starts[0].seed}"
    assert placement_seed("train", 1, 0, 0) != placement_seed("train", 2, 0, 0)  # suites apart too
    with pytest.raises(ValueError, match="purpose must be one of"):
        placement_seed("test", 1, 0, 0)
    with pytest.raises(ValueError, match="at least one task"):
        placement_starts("libero_spatial", [], 1, "train")


@pytest.mark.sim
def test_a_fresh_placement_is_checked_against_the_benchmarks_init_states(contract):
    """Restored from its seed, a placement lies centimetres from the nearest of the task's 50
    benchmark init states (reproducibly); a benchmark init state itself is refused."""
    from worldenv_core.envs.recording import cached_env
    from worldenv_core.envs.replay import restore

    c = contract()
    env = cached_env(c.suite, 0, c.cameras, c.image_size, render=False)
    start = placement_starts(c.suite, [0], 1, "validation")[0]
    frame = restore(env, start)
    nq = env.sim.model.nq
    gap = benchmark_distance(c.suite, 0, frame.sim_state, nq)
    assert gap > 1e-3, gap  # objects and arm elsewhere than in any evaluation start
    np.testing.assert_array_equal(restore(env, start).sim_state[1:], frame.sim_state[1:])  # seeded: the same scene
    bench = env.reset(init_state=3)
    with pytest.raises(BenchmarkOverlap, match="is a benchmark init state"):
        check_not_benchmark(c.suite, 0, bench.sim_state, nq, seed=0)
