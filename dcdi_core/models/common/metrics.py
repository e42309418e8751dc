"""PSNR and SSIM, in numpy and (for training) in torch.

SSIM is Wang et al. (2004) as the paper's code and scikit-image compute it: a
Gaussian window of 11 taps (sigma 1.5, truncated at 3.5 sigma), population
(co)variances, C1 = (0.01 L)^2, C2 = (0.03 L)^2 with L the data range, and
the mean of the SSIM map over the pixels whose window lies inside the image
(the "valid" region). Images are (..., C, H, W): each channel is an image, and
the result is the mean over channels (one number per leading index).

PSNR is 10 log10(L^2 / MSE) per image (leading index), over all its channels
and pixels. ``quantize_8bit`` gives the paper's 8-bit figures: its 49.29 dB
and 0.9953 are PSNR and SSIM of peak-normalised PSFs written as 8-bit images
(round(255 x), L = 255).

The torch functions import torch when called; this module imports numpy only.
"""
from __future__ import annotations

import math

import numpy as np

from ...errors import InputRangeError

WINDOW = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03


def gaussian_window(size: int = WINDOW, sigma: float = SIGMA) -> np.ndarray:
    """The normalised 1-D Gaussian (size,) of the SSIM window (float64)."""
    if size < 1 or size % 2 == 0:
        raise InputRangeError("window size", size, "odd integer >= 1")
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _check_pair(a, b, data_range):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise InputRangeError("image shapes", (a.shape, b.shape), "two arrays of the same shape")
    if data_range is None or not (float(data_range) > 0 and math.isfinite(float(data_range))):
        raise InputRangeError("data_range", data_range, "a finite number > 0 (e.g. 1.0 or 255)")
    return a, b, float(data_range)


def psnr(a, b, data_range: float) -> np.ndarray | float:
    """PSNR in dB of images (..., C, H, W) (or (H, W)): one value per image
    (inf where they are equal)."""
    a, b, L = _check_pair(a, b, data_range)
    axes = tuple(range(-min(a.ndim, 3), 0))
    mse = ((a - b) ** 2).mean(axis=axes)
    with np.errstate(divide="ignore"):
        out = 10.0 * np.log10(L * L / mse)
    return float(out) if np.ndim(out) == 0 else out


def _filter_valid(x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of (..., H, W) with g along both axes."""
    n = len(g)
    h, w = x.shape[-2:]
    rows = sum(g[i] * x[..., i:h - n + 1 + i, :] for i in range(n))
    return sum(g[i] * rows[..., :, i:w - n + 1 + i] for i in range(n))


def ssim_map(a, b, data_range: float, *, window: int = WINDOW, sigma: float = SIGMA) -> np.ndarray:
    """The SSIM map of images (..., H, W) over the valid region: (..., H -
    window + 1, W - window + 1); entry (i, j) belongs to pixel (i + window //
    2, j + window // 2), the centre of its window."""
    a, b, L = _check_pair(a, b, data_range)
    if a.shape[-1] < window or a.shape[-2] < window:
        raise InputRangeError("image size", a.shape[-2:], f">= {window} x {window} pixels (the SSIM window)")
    g = gaussian_window(window, sigma)
    c1, c2 = (K1 * L) ** 2, (K2 * L) ** 2
    mu_a, mu_b = _filter_valid(a, g), _filter_valid(b, g)
    var_a = _filter_valid(a * a, g) - mu_a * mu_a
    var_b = _filter_valid(b * b, g) - mu_b * mu_b
    cov = _filter_valid(a * b, g) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))


def ssim(a, b, data_range: float, *, window: int = WINDOW, sigma: float = SIGMA) -> np.ndarray | float:
    """SSIM of images (..., C, H, W) (or (H, W)): the mean over channels of
    each channel's mean SSIM over the valid region; one value per image."""
    s = ssim_map(a, b, data_range, window=window, sigma=sigma)
    per_channel = s.mean(axis=(-2, -1))
    out = per_channel if s.ndim == 2 else per_channel.mean(axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def quantize_8bit(x) -> np.ndarray:
    """round(255 x) clipped to [0, 255], as float64 (the paper's 8-bit images)."""
    return np.clip(np.round(np.asarray(x, dtype=np.float64) * 255.0), 0.0, 255.0)


def relative_l1(p, ref) -> np.ndarray | float:
    """sum |p - ref| / sum ref per channel, averaged over channels: one value
    per kernel (..., C, k, k); the metric of `python -m lab report psf-accuracy`."""
    p = np.asarray(p, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    l1 = np.abs(p - ref).sum(axis=(-1, -2)) / np.maximum(ref.sum(axis=(-1, -2)), 1e-300)
    out = l1.mean(axis=-1)
    return float(out) if np.ndim(out) == 0 else out


# --------------------------------------------------------------------- torch
def psnr_torch(a, b, data_range: float):
    """PSNR in dB per image of tensors (N, C, H, W): shape (N,)."""
    import torch

    mse = ((a - b) ** 2).flatten(1).mean(dim=1)
    return 10.0 * torch.log10(data_range ** 2 / mse)


def ssim_torch(a, b, data_range: float, *, window: int = WINDOW, sigma: float = SIGMA):
    """SSIM per image of tensors (N, C, H, W), as :func:`ssim`: shape (N,).
    Differentiable (usable as a loss)."""
    import torch
    import torch.nn.functional as F

    n, c, h, w = a.shape
    if h < window or w < window:
        raise InputRangeError("image size", (h, w), f">= {window} x {window} pixels (the SSIM window)")
    g = torch.as_tensor(gaussian_window(window, sigma), dtype=a.dtype, device=a.device)
    gr = g.view(1, 1, window, 1).expand(c, 1, window, 1)
    gc = g.view(1, 1, 1, window).expand(c, 1, 1, window)

    def filt(x):
        return F.conv2d(F.conv2d(x, gr, groups=c), gc, groups=c)

    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    mu_a, mu_b = filt(a), filt(b)
    var_a = filt(a * a) - mu_a * mu_a
    var_b = filt(b * b) - mu_b * mu_b
    cov = filt(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return s.mean(dim=(-2, -1)).mean(dim=-1)


# ----------------------------------------------------------------- PSF scores
def psf_scores(pred, ref, *, scale: str) -> dict:
    """Figures of predicted PSFs (n, 3, k, k) against references (n, 3, k, k),
    each the mean over the n PSFs:

    - ``psnr_8bit``, ``ssim_8bit``: the paper's scale: both peak-normalised
      per channel (a ``scale="peak"`` prediction as it is, a ``"sum"`` one by
      its own peak), as 8-bit images (L = 255); each PSF's PSNR is capped at
      100 dB (identical 8-bit images), so the mean can hide a few bad PSFs
      among many exact ones: ``psnr_8bit_median`` and ``psnr_8bit_worst``
      (the lowest) say how they spread;
    - ``psnr_sum``: both summing to 1 per channel, L = the reference's peak;
    - ``rel_l1``: both summing to 1, sum |P - R| / sum R (mean over channels),
      the metric of `python -m lab report psf-accuracy`.
    """
    if scale not in ("sum", "peak"):
        raise InputRangeError("scale", scale, "'sum' or 'peak'")
    p = np.asarray(pred, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)

    def by(x, how):
        s = x.max(axis=(-1, -2), keepdims=True) if how == "peak" else x.sum(axis=(-1, -2), keepdims=True)
        return x / np.where(s > 0, s, 1.0)

    p_peak, r_peak = (p if scale == "peak" else by(p, "peak")), by(r, "peak")
    p_sum, r_sum = by(p, "sum"), by(r, "sum")
    q_p, q_r = quantize_8bit(p_peak), quantize_8bit(r_peak)
    each = np.minimum(psnr(q_p, q_r, 255.0), 100.0)
    out = {"psnr_8bit": float(np.mean(each)), "psnr_8bit_median": float(np.median(each)),
           "psnr_8bit_worst": float(np.min(each)),
           "ssim_8bit": float(np.mean(ssim(q_p, q_r, 255.0))) if p.shape[-1] >= WINDOW else None}
    mse = ((p_sum - r_sum) ** 2).mean(axis=(-3, -2, -1))
    peak = r_sum.max(axis=(-3, -2, -1))
    with np.errstate(divide="ignore"):
        out["psnr_sum"] = float(np.mean(np.minimum(10 * np.log10(peak ** 2 / mse), 100.0)))
    out["rel_l1"] = float(np.mean(relative_l1(p_sum, r_sum)))
    out["n"] = int(len(p))
    return out


def depth_scores(pred_m, true_m) -> dict:
    """Monocular-depth metrics over the pixels whose true depth is finite and
    positive (NaN, infinity, sky excluded): AbsRel = mean |p - t| / t, RMSE
    (m), and delta1 = share with max(p / t, t / p) < 1.25; 'pixels' the count.
    Predictions are floored at 1 mm."""
    p = np.asarray(pred_m, dtype=np.float64)
    t = np.asarray(true_m, dtype=np.float64)
    if p.shape != t.shape:
        raise InputRangeError("depth shapes", (p.shape, t.shape), "two arrays of the same shape")
    sel = np.isfinite(t) & (t > 0)
    if not sel.any():
        raise InputRangeError("true depth", "no finite positive value", "some pixels with a metric depth")
    p, t = np.maximum(np.where(np.isfinite(p[sel]), p[sel], 1e6), 1e-3), t[sel]
    ratio = np.maximum(p / t, t / p)
    return {"abs_rel": float(np.mean(np.abs(p - t) / t)), "rmse": float(np.sqrt(np.mean((p - t) ** 2))),
            "delta1": float(np.mean(ratio < 1.25)), "pixels": int(sel.sum())}
