"""The keyframe strip: frames picked at env steps, the picture drawn, bad input named before any model loads."""
import numpy as np
import pytest
import torch

from analysis.keyframe_strip import as_image, draw, main, pick


def test_frames_are_picked_by_step_and_a_stopped_rollout_is_darkened():
    frames = [np.full((4, 4, 3), 10 * i, dtype=np.uint8) for i in range(3)]  # chunk boundaries 0, 8, 16
    out = pick(frames, [0, 8, 16, 24], per_frame=8)
    assert [int(f[0, 0, 0]) for f in out] == [0, 10, 20, 8]  # past the end: the last frame at 40 %


def test_frames_of_either_dtype_become_images():
    f = torch.zeros(3, 2, 2)
    f[0] = 1.0
    img = as_image(f)
    assert img.dtype == np.uint8 and img.shape == (2, 2, 3) and img[0, 0].tolist() == [255, 0, 0]
    assert as_image(torch.full((3, 2, 2), 7, dtype=torch.uint8))[1, 1].tolist() == [7, 7, 7]


def test_the_strip_is_written(tmp_path):
    rows = [("recorded", [np.zeros((8, 8, 3), np.uint8)] * 2), ("model\nno success", [np.ones((8, 8, 3), np.uint8)] * 2)]
    path = draw(rows, [0, 16], tmp_path / "s.png", title="t")
    assert path.stat().st_size > 0 and not list(tmp_path.glob("*.tmp*"))


def test_bad_input_is_named_before_any_model_loads(tmp_path, capsys):
    common = ["+task=tiny", "--policy", str(tmp_path), "--worldsim", str(tmp_path), "--out", str(tmp_path / "o.png")]
    with pytest.raises(SystemExit):
        main([*common, "--episodes", "x.mcap", "--depth", "0.6", "0.2"])
    assert "--depth: a context depth [lo, hi] needs 0 <= lo < hi <= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*common, "--episodes", str(tmp_path / "none*.mcap")])
    assert "no recorded episode matches" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*common, "--episodes", "x.mcap", "--every", "0"])
    assert "--every and --horizon must be positive" in capsys.readouterr().err
