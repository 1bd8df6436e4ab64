"""The paired SFT-vs-post-trained test against hand-computed values."""
import math

import pytest

import numpy as np

from worldenv_core.errors import ConfigError
from worldenv_core.stats import paired_difference_ci, paired_success_test, permutation_p, spearman, wilson


def test_paired_success_test_by_hand():
    a = {0: True, 1: True, 2: False, 3: False, 4: False, 5: False, 6: False, 7: True, 8: False}
    b = {0: True, 1: False, 2: True, 3: True, 4: True, 5: True, 6: True, 7: True, 99: True}  # 8 and 99 unpaired
    t = paired_success_test(a, b)
    assert (t["episodes"], t["only_a"], t["only_b"]) == (8, 1, 5)
    assert math.isclose(t["p_value"], 2 * (1 + 6) / 2 ** 6)  # two-sided exact binomial on 6 discordant, k <= 1


def test_paired_success_test_without_disagreement_is_uninformative():
    same = {i: i % 2 == 0 for i in range(10)}
    assert paired_success_test(same, same) == {"episodes": 10, "only_a": 0, "only_b": 0, "p_value": 1.0}
    balanced = paired_success_test({0: True, 1: False}, {0: False, 1: True})
    assert balanced["p_value"] == 1.0


def test_cluster_bootstrap_resamples_whole_clusters():
    import numpy as np

    from worldenv_core.stats import cluster_bootstrap_ci

    values = np.array([0.0, 0.0, 1.0, 1.0])
    # two clusters that each agree within: a resample's mean is 0, 0.5 or 1, never 0.25
    low, high = cluster_bootstrap_ci(lambda i: float(values[i].mean()), ["a", "a", "b", "b"], n_boot=400)
    assert low == 0.0 and high == 1.0
    means = []
    cluster_bootstrap_ci(lambda i: means.append(float(values[i].mean())) or 0.0, ["a", "a", "b", "b"], n_boot=200)
    assert set(means) == {0.0, 0.5, 1.0}  # whole clusters drawn; a row-level resample would also give 0.25, 0.75
    # one cluster per row of many identical rows: no spread; undefined statistics give nan
    assert cluster_bootstrap_ci(lambda i: 1.0, list(range(20))) == [1.0, 1.0]
    assert np.isnan(cluster_bootstrap_ci(lambda i: float("nan"), [0, 1])).all()


def test_spearman_counts_rates_that_differ_by_rounding_as_ties():
    assert 0.1 + 0.2 != 0.3  # the same rate, summed in another order
    assert spearman([0.1 + 0.2, 0.3, 0.5], [1, 2, 3]) == spearman([0.3, 0.3, 0.5], [1, 2, 3])
    assert spearman([0.3, 0.3, 0.5], [1, 2, 3]) == pytest.approx(0.866, abs=1e-3)


def test_paired_difference_ci_by_hand():
    # 10 only-a, 30 only-b of 200: diff 0.1, se = sqrt((40/200 - 0.01) / 200) = sqrt(0.00095)
    low, high = paired_difference_ci(10, 30, 200)
    half = 1.96 * math.sqrt(0.00095)
    assert (low, high) == pytest.approx((0.1 - half, 0.1 + half))
    assert paired_difference_ci(0, 0, 50) == [0.0, 0.0]  # no discordant episode: no spread
    assert paired_difference_ci(5, 5, 100, level=0.99)[1] > paired_difference_ci(5, 5, 100)[1]
    with pytest.raises(ValueError, match="at least one episode"):
        paired_difference_ci(0, 0, 0)


def test_the_permutation_p_is_exact_over_every_relabelling():
    # 3 vs 3 fully separated: only the observed split and its mirror are as extreme, 2 of C(6, 3) = 20
    assert permutation_p(np.array([0.7, 0.8, 0.9]), np.array([0.1, 0.2, 0.3])) == pytest.approx(2 / 20)
    assert permutation_p(np.array([0.7, 0.8, 0.9]), np.array([0.1, 0.2, 0.3]), greater=True) == pytest.approx(1 / 20)
    assert permutation_p(np.array([0.1, 0.2, 0.3]), np.array([0.7, 0.8, 0.9]), greater=True) == 1.0
    assert permutation_p(np.array([0.5, 0.5]), np.array([0.5, 0.5])) == 1.0
    with pytest.raises(ConfigError, match="too many"):
        permutation_p(np.zeros(20), np.zeros(20))


def test_wilson_interval_matches_the_textbook_figures():
    lo, hi = wilson(69, 100)
    assert lo == pytest.approx(0.5937, abs=1e-4) and hi == pytest.approx(0.7722, abs=1e-4)  # by hand
    assert wilson(0, 10)[0] == pytest.approx(0.0, abs=1e-12) and wilson(10, 10)[1] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        wilson(0, 0)
