"""An evaluation's episode GIFs: each termination mode's episode, as many frames as a GIF plays, and
only those frames rendered (a 280-step episode: 60 renders, not 280)."""
import pickle
import zlib

import imageio.v2 as imageio
import numpy as np
import pytest

from tests.stages.conftest import stage_cfg
from worldenv_core.manifest import Manifest
from worldenv_core.viz import MONTAGE_FRAMES, video_picks


def test_video_picks_spread_a_montages_frames_over_the_episode():
    picks = video_picks(281)
    assert len(picks) == MONTAGE_FRAMES and picks[0] == 0 and picks[-1] == 280 and np.all(np.diff(picks) > 0)
    assert list(video_picks(5)) == [0, 1, 2, 3, 4]  # a short episode: every frame
    assert list(video_picks(9, 5)) == [0, 2, 4, 6, 8]


@pytest.mark.sim
def test_an_evaluation_renders_only_the_frames_its_gifs_play(tiny_models):
    import stages.evaluate.run as evaluate_stage

    exp = tiny_models
    evaluate_stage.run(stage_cfg("evaluate", exp, "policy_from=sft", "termination=all", "init_states=1", "workers=1",
                                 "progress=false", "videos_per_task=1", "task.max_steps=96"))
    kept = [pickle.loads(zlib.decompress(p.read_bytes())) for p in (exp / "evaluate" / "jobs").glob("*.pkl.z")]
    job = next(j for j in kept if j["videos"])
    rows, video = job["rows"], job["videos"][0]
    assert {r["termination"] for r in rows} == {"oracle", "fixed", "reflector"}
    fixed = next(r for r in rows if r["termination"] == "fixed")
    assert fixed["steps"] + 1 > MONTAGE_FRAMES  # long enough that a GIF skips frames
    # what was rendered: the union of the three modes' picks, nothing more
    assert sorted(video) == sorted({int(j) for r in rows for j in video_picks(r["steps"] + 1)})
    assert len(video) < fixed["steps"] + 1
    for r in rows:
        rec = Manifest(exp).latest("evaluate", task="tiny", termination=r["termination"])
        gif = next((exp / rec.metrics["report_dir"]).glob("videos/task00_init00_*.gif"))
        frames = imageio.mimread(gif)
        assert len(frames) == min(MONTAGE_FRAMES, r["steps"] + 1)
        # the GIF's last frame is the mode's last frame (where it stopped), as rendered for the job (a GIF's
        # palette changes pixels a little)
        assert np.abs(np.asarray(frames[-1])[..., :3].astype(int) - video[r["steps"]]).mean() < 3
