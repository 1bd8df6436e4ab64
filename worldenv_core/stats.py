"""The statistics the project's figures rest on, each exact where it can be: classification metrics
(the reflector's verdict: AUROC, F1), rank correlation, intervals by resampling whole clusters, the
exact McNemar test and paired interval for two policies on the same episodes, the sign test's
binomial tail, the exact permutation test over seeds, and the Wilson interval of a success rate."""

from __future__ import annotations

import itertools
import math

import numpy as np

from worldenv_core.errors import ConfigError


# ---- binary classification (the reflector's per-step success prediction) ----

def auroc(scores, labels) -> float:
    """Area under the ROC curve by the rank-sum (Mann-Whitney) formula, ties counted half;
    nan when only one class is present."""
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    n_pos, n_neg = int(labels.sum()), int((~labels).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.cumsum(counts) - (counts - 1) / 2)[inverse]  # 1-based, ties share their mean rank
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def spearman(x, y) -> float:
    """Spearman's rank correlation (ties share their mean rank); nan when either side is constant."""
    def ranks(v):
        # rounded: rates summed in another order (0.1 + 0.2 against 0.3) are the same rate, so a tie
        _, inverse, counts = np.unique(np.round(np.asarray(v, dtype=float), 9), return_inverse=True, return_counts=True)
        return (np.cumsum(counts) - (counts - 1) / 2)[inverse]

    rx, ry = ranks(x), ranks(y)
    if len(rx) < 2 or rx.std() == 0 or ry.std() == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def binary_metrics(scores, labels, threshold: float) -> dict:
    """Accuracy, precision, recall, F1 of `scores > threshold`, and AUROC, with the counts."""
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    pred = scores > threshold
    tp, fp = int((pred & labels).sum()), int((pred & ~labels).sum())
    fn, tn = int((~pred & labels).sum()), int((~pred & ~labels).sum())
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    return {"accuracy": (tp + tn) / max(1, len(labels)), "precision": precision, "recall": recall,
            "f1": 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else float("nan"),
            "auroc": auroc(scores, labels), "tp": tp, "fp": fp, "fn": fn, "tn": tn, "n": int(len(labels))}


def cluster_bootstrap_ci(statistic, clusters, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> list[float]:
    """[low, high] percentile interval of `statistic(rows)` over resamples of whole clusters with
    replacement (`clusters`: a cluster label per row). Rows of one cluster (the rollouts of one
    context) are not independent draws, so resampling rows alone would understate the spread.
    Resamples where the statistic is undefined (nan: e.g. one class only) are dropped; [nan, nan]
    when fewer than half remain."""
    labels = np.asarray(clusters)
    groups = [np.flatnonzero(labels == c) for c in np.unique(labels)]
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(n_boot):
        rows = np.concatenate([groups[i] for i in rng.integers(len(groups), size=len(groups))])
        v = statistic(rows)
        if v == v:
            values.append(v)
    if len(values) < n_boot / 2:
        return [float("nan"), float("nan")]
    tail = 100 * (1 - level) / 2
    return [float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))]


def fair_coin_tail(n: int, k: int) -> float:
    """P(X <= k) for X ~ Binomial(n, 1/2), exactly: the tail of a sign test (by symmetry also P(X >= n - k))."""
    return sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n


def paired_success_test(a: dict, b: dict) -> dict:
    """Two policies' successes on the same episodes ({episode key: bool}, e.g. (task, init state)):
    how many only `a` solved, how many only `b` solved, and the exact two-sided McNemar p-value
    (a binomial test on those discordant episodes). Episodes both solve or both fail carry no
    information about which policy is better, so this is far sharper than comparing two rates."""
    keys = sorted(set(a) & set(b))
    only_a = sum(bool(a[k]) and not b[k] for k in keys)
    only_b = sum(bool(b[k]) and not a[k] for k in keys)
    n, k = only_a + only_b, min(only_a, only_b)
    p = min(1.0, 2 * fair_coin_tail(n, k)) if n else 1.0
    return {"episodes": len(keys), "only_a": only_a, "only_b": only_b, "p_value": p}


def paired_difference_ci(only_a: int, only_b: int, n: int, level: float = 0.95) -> list[float]:
    """[low, high] interval of the success difference b - a on n paired episodes, from the
    discordant counts (the Wald interval for paired proportions, without continuity correction;
    the exact test is `paired_success_test`). Episodes both solve or both fail narrow it through n."""
    if n <= 0:
        raise ValueError("a paired difference needs at least one episode")
    z = {0.9: 1.6449, 0.95: 1.9600, 0.99: 2.5758}[level]
    diff = (only_b - only_a) / n
    se = math.sqrt(max(0.0, (only_a + only_b) / n - diff ** 2) / n)
    return [diff - z * se, diff + z * se]


# ---- seeds: procedures compared over their seeds' success rates ----

def permutation_p(a: np.ndarray, b: np.ndarray, greater: bool = False) -> float:
    """Exact p of the difference in means over every relabelling of the pooled values: two-sided, or with
    `greater` one-sided (how often a relabelled `a` beats `b` by at least as much as the real one does)."""
    pooled = np.concatenate([a, b])
    if math.comb(len(pooled), len(a)) > 200_000:
        raise ConfigError(f"{math.comb(len(pooled), len(a))} relabellings of {len(pooled)} policies: too many to enumerate")
    picked = np.array([pooled[list(s)].sum() for s in itertools.combinations(range(len(pooled)), len(a))])
    diffs = picked / len(a) - (pooled.sum() - picked) / len(b)
    observed = a.mean() - b.mean()
    if not greater:
        diffs, observed = np.abs(diffs), abs(observed)
    return float((diffs >= observed - 1e-12).mean())


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success rate (95 % by default)."""
    if n <= 0:
        raise ValueError("an interval needs at least one episode")
    p = successes / n
    centre, half = p + z * z / (2 * n), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (centre - half) / (1 + z * z / n), (centre + half) / (1 + z * z / n)
