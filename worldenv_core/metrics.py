"""Image metrics for world-model fidelity, batched in torch (images in [0, 1], (..., 3, H, W)).
The statistics (classification metrics, paired tests, intervals) are in `worldenv_core.stats`."""

from __future__ import annotations

import torch
from torch.nn import functional as F


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image (...,); `mask` (..., H, W) bool: over those pixels only."""
    err = (pred.float() - target.float()).pow(2)
    if mask is None:
        mse = err.flatten(-3).mean(-1)
    else:
        mse = (err.mean(-3) * mask).flatten(-2).sum(-1) / mask.flatten(-2).sum(-1).clamp(min=1)
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
