"""Image metrics for world-model fidelity, batched in torch (images in [0, 1], (..., 3, H, W)),
classification metrics for the reflector, and the paired test that compares two policies."""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image (...,)."""
    mse = (pred.float() - target.float()).pow(2).flatten(-3).mean(-1)
    return 10 * torch.log10(1.0 / mse.clamp(min=1e-10))


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_map(pred: torch.Tensor, target: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Local structural similarity (Wang et al. 2004; Gaussian window 11, sigma 1.5, per channel,
    averaged over channels): (..., 3, H, W) -> (..., H - window + 1, W - window + 1), valid
    convolution so there are no padding artefacts."""
    lead = pred.shape[:-3]
    x = pred.float().reshape(-1, *pred.shape[-3:])
    y = target.float().reshape(-1, *target.shape[-3:])
    c = x.shape[1]
    w = _gaussian_window(window).to(x.device)[None, None].expand(c, 1, -1, -1)
    blur = lambda v: F.conv2d(v, w, groups=c)  # noqa: E731
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx ** 2, blur(y * y) - my ** 2, blur(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))
    return s.mean(1).reshape(*lead, *s.shape[-2:])


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Structural similarity per image (...,): the mean of `ssim_map`."""
    return ssim_map(pred, target, window).flatten(-2).mean(-1)


# ---- binary classification (the reflector's per-step success prediction) ----

def auroc(scores, labels) -> float:
    """Area under the ROC curve by the rank-sum (Mann-Whitney) formula, ties counted half;
    nan when only one class is present."""
    import numpy as np

    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    n_pos, n_neg = int(labels.sum()), int((~labels).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.cumsum(counts) - (counts - 1) / 2)[inverse]  # 1-based, ties share their mean rank
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def spearman(x, y) -> float:
    """Spearman's rank correlation (ties share their mean rank); nan when either side is constant."""
    import numpy as np

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
    import numpy as np

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
    import numpy as np

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
