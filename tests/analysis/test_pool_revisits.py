"""The pool-revisit split on a journal written as the stage writes one: the starts an earlier
iteration drew (from the run's seed, as the stage draws them) against the rest, pooled and by task."""
import json
import pickle
import zlib

import pytest

from analysis.pool_revisits import main, seen_before, split
from stages.post_train_loop.training import placements
from worldenv_core.stage import compose_config, task_contract

RUN = ["+task=tiny", "scale=tiny", "rl.contexts=placements", "rl.placement_pool=6", "rl.contexts_per_iteration=2",
       "rl.n_rollouts=2", "seed=3"]


def test_the_starts_an_earlier_iteration_trained_on_against_the_rest(tmp_path):
    start = placements(task_contract(compose_config("post_train_loop", ["scale=small", *RUN])))
    pool = {k: start(k)[0] for k in range(6)}
    seen = seen_before(3, 2, 6, 2, lambda k: pool[k].key)  # what iteration 1 drew
    assert 1 <= len(seen) <= 2 and seen <= {s.key for s in pool.values()}
    assert seen_before(3, 3, 6, 2, lambda k: pool[k].key) >= seen  # and iteration 2 on top
    judged = [next(s for s in pool.values() if s.key in seen), next(s for s in pool.values() if s.key not in seen)]
    folder = tmp_path / "journal"
    folder.mkdir()
    for i in range(4):  # the seen start's 2 rollouts succeed, the unseen one's fail
        result = {"index": i, "start": judged[i // 2], "error": None, "first_success": 10 if i < 2 else None}
        (folder / f"{i:05d}.rollout").write_bytes(zlib.compress(pickle.dumps(((i,), result))))
    out = main([*RUN, "--journal", str(folder), "--iteration", "2", "--json", str(tmp_path / "split.json")])
    assert out["seen"]["success"] == 1.0 and out["unseen"]["success"] == 0.0
    assert json.loads((tmp_path / "split.json").read_text())["seen"]["rollouts"] == 2
    with pytest.raises(SystemExit):  # the first iteration has seen nothing; a run without a pool has no revisits
        main([*RUN, "--journal", str(folder), "--iteration", "1"])
    with pytest.raises(SystemExit):
        main(["+task=tiny", "scale=tiny", "--journal", str(folder), "--iteration", "2"])


def test_the_task_balanced_difference_compares_within_tasks_only():
    outcomes = {"task0/a": [8, 8], "task0/b": [4, 8], "task1/c": [0, 8], "task2/d": [2, 8]}
    out = split(outcomes, {"task0/a", "task1/c"})
    assert out["seen"]["success"] == pytest.approx(0.5) and out["unseen"]["success"] == pytest.approx(0.375)
    assert out["tasks_with_both"] == 1 and out["task_balanced_difference"] == pytest.approx(0.5)
