"""Seeded endless batches: exact resume, plain and weighted."""
from itertools import islice

import pytest
import torch
from torch.utils.data import TensorDataset

from worldenv_core.training import batches


def _ids(stream, n):
    return [b[0].tolist() for b in islice(stream, n)]


def test_batches_cover_each_epoch_once_and_resume_at_any_step():
    data = TensorDataset(torch.arange(10))
    full = _ids(batches(data, 3, seed=0), 9)  # 3 batches an epoch
    assert sorted(sum(full[:3], [])) == sorted(set(sum(full[:3], [])))  # no repeat inside an epoch
    assert _ids(batches(data, 3, seed=0, start_step=4), 5) == full[4:]


def test_weighted_batches_draw_in_proportion_and_resume_exactly():
    data = TensorDataset(torch.arange(100))
    weights = torch.where(torch.arange(100) < 10, 9.0, 1.0)  # items 0-9 carry half the weight (90 of 180)
    drawn = torch.tensor(sum(_ids(batches(data, 10, seed=1, weights=weights), 200), []))
    assert abs(float((drawn < 10).float().mean()) - 0.5) < 0.03  # 2,000 draws: a 3-sigma band is ~0.034
    assert _ids(batches(data, 10, seed=1, weights=weights, start_step=37), 30) == \
        _ids(batches(data, 10, seed=1, weights=weights), 67)[37:]
    never = torch.ones(100)
    never[:50] = 0
    assert min(sum(_ids(batches(data, 10, seed=1, weights=never), 20), [])) >= 50


@pytest.mark.parametrize("weights", [torch.ones(9), -torch.ones(10), torch.zeros(10)])
def test_bad_weights_are_refused_before_any_batch(weights):
    with pytest.raises(ValueError, match="weights must be 10 non-negative"):
        next(batches(TensorDataset(torch.arange(10)), 3, seed=0, weights=weights))
