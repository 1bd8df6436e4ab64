"""Plots and episode montages: written whole (no temporary file left), readable back."""
import json

import imageio.v2 as imageio
import numpy as np

from worldenv_core.viz import montage_video, plot_history, tile


def test_tile_lays_frames_out_in_a_grid_row_by_row():
    frames = [np.full((2, 3, 3), i, dtype=np.uint8) for i in range(5)]
    grid = tile(frames)
    assert grid.shape[2] == 3 and grid.shape[0] % 2 == 0 and grid.shape[1] % 3 == 0
    assert grid[0, 0, 0] == 0 and grid[0, 3, 0] == 1  # the second frame right of the first


def test_montage_plays_a_short_and_a_long_episode_together(tmp_path):
    short = np.zeros((3, 8, 8, 3), np.uint8)
    long = np.arange(9, dtype=np.uint8)[:, None, None, None].repeat(8, 1).repeat(8, 2).repeat(3, 3) * 25  # each frame its own
    path = montage_video([short, long], tmp_path / "m.gif", max_frames=5)
    frames = imageio.mimread(path)
    assert len(frames) == 5 and [p.name for p in tmp_path.iterdir()] == ["m.gif"]


def test_plot_history_draws_each_curve_and_keeps_the_history_beside_it(tmp_path):
    history = [{"step": 0, "validation_success": 0.6}, {"step": 1, "loss": 2.0},
               {"step": 2, "loss": 1.0, "validation_success": 0.7}]
    path = plot_history(history, tmp_path / "curves.png", "a run")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "curves.json").read_text()) == history
    assert sorted(p.name for p in tmp_path.iterdir()) == ["curves.json", "curves.png"]
