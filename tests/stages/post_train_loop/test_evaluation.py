"""post_train_loop's plots that need no simulator."""
import json

from stages.post_train_loop.evaluation import plot_pack_runs


def test_pack_runs_are_drawn_side_by_side_from_their_histories(tmp_path):
    files = {}
    for name, rate in (("a", 0.2), ("b", 0.6)):
        history = [{"step": 0, "imagined_success": rate}] + [
            {"step": i, "mean_reward": rate, "reflector_success_rate": rate, "kept_groups": 0.1} for i in range(1, 13)]
        files[name] = tmp_path / f"{name}.json"
        files[name].write_text(json.dumps(history))
    out = plot_pack_runs(files, tmp_path / "runs.png", "two runs")
    assert out.exists() and out.stat().st_size > 10_000


def test_the_validation_set_is_split_over_the_workers_even_on_one_task():
    """A job per task; one task trained on is split into as many parts as workers, the same
    placements in all (the set does not depend on how it is run)."""
    from stages.post_train_loop.evaluation import validation_jobs
    from worldenv_core.stage import compose_config, task_contract

    def placements(jobs):
        return sorted((j.task_id, s) for j in jobs for s in j.placements)
    every = task_contract(compose_config("post_train_loop", ["scale=small", "+task=libero_spatial"]))
    by_task = validation_jobs("policy", every, 100, 2)
    assert [j.task_id for j in by_task] == list(range(10)) and all(len(j.placements) == 10 for j in by_task)
    one = task_contract(compose_config("post_train_loop", ["scale=small", "+task=libero_spatial", "task.task_ids=[4]"]))
    split = validation_jobs("policy", one, 100, 2)
    assert [(j.task_id, len(j.placements)) for j in split] == [(4, 50), (4, 50)]
    assert placements(split) == placements(validation_jobs("policy", one, 100, 1))
    assert len(validation_jobs("policy", one, 3, 8)) == 3  # no empty job
