"""The verdict-by-lever plot's rows: one per pairing, the newest judgement kept, precision from the hack rate."""
import math

from stages.evaluate_imagination.levers import lever_rows, plot_levers


def test_the_newest_judgement_of_a_pairing_wins_and_sorts_last(tmp_path):
    rows = lever_rows([("wm", "r1", {"auroc": 0.5, "f1": 0.0, "hack_rate": float("nan"), "rollouts": 80}),
                       ("wm", "r2", {"auroc": 0.6, "f1": 0.4, "hack_rate": 0.25, "rollouts": 80}),
                       ("wm", "r1", {"auroc": 0.7, "f1": 0.5, "hack_rate": 0.5, "rollouts": 40})])
    assert list(rows) == ["wm + r2", "wm + r1"]
    assert rows["wm + r1"] == {"auroc": 0.7, "f1": 0.5, "precision": 0.5, "rollouts": 40}
    assert math.isclose(rows["wm + r2"]["precision"], 0.75)
    undefined = lever_rows([("wm", "r0", {"auroc": float("nan"), "f1": 0.0, "hack_rate": None, "rollouts": 8})])
    assert undefined["wm + r0"]["precision"] is None
    path = plot_levers({**rows, **undefined}, tmp_path / "levers.png")
    assert path.exists() and path.stat().st_size > 1000
