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
