"""The reflector-past ablation: verdict scores per side and the best R over a pair side's checks, with and without
a keyframe's recorded past."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from analysis.reflector_past import best_score, verdict_scores
from tests.worldenv_core.models.test_reflector import small_config


def test_verdict_scores_count_what_the_verdict_said_against_the_real_outcome():
    outcome = np.array([True, True, True, False, False])
    said = np.array([True, False, False, True, False])
    got = verdict_scores(outcome, said)
    assert got["said_success"] == pytest.approx(0.4) and got["recall"] == pytest.approx(1 / 3)
    assert got["precision"] == pytest.approx(0.5) and got["f1"] == pytest.approx(0.4)
    silent = verdict_scores(outcome, np.zeros(5, bool))
    assert np.isnan(silent["precision"]) and silent["recall"] == 0 and silent["f1"] == 0


def test_the_best_score_is_the_highest_r_after_the_first_frame_of_the_whole_prefix():
    torch.manual_seed(0)
    model = instantiate(small_config(max_frames=8)).eval()
    past, frames = (torch.randint(0, 255, (n, 3, 16, 16), dtype=torch.uint8) for n in (3, 4))
    lang = torch.randn(16)
    for with_past in (past, None):
        head = [] if with_past is None else [with_past]
        want = max(float(model.score_video(torch.cat([*head, frames[:t + 1]]), lang)) for t in range(1, 4))
        assert best_score(model, lang, frames, with_past) == pytest.approx(want, abs=1e-5)
    assert best_score(model, lang, frames, past) != pytest.approx(best_score(model, lang, frames, None), abs=1e-5)
