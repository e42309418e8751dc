"""Depth as the network sees it (numpy; the same for training and inference).

``minmax`` (the paper's): depth clamped to [0.1, 10] m, then min-max
normalised over the crop (per crop in training; over the whole image at
inference, so that tiles of one image share one scale) to [0, 1]; a crop of
one depth gives 0.

``diopter`` (ours): metric inverse depth, which the defocus blur follows:
``DIOPTER_SCALE_M / max(depth, 0.1 m)``, so 0.7 m (the PSF library's near
limit) is 1, 10 m is 0.07 and infinity 0; the same scale for every crop and
image (no per-crop statistics).

Invalid depth (NaN, <= 0; also where the lens images nothing) is taken as
the far clamp, 10 m (minmax) or infinity (diopter).
"""
from __future__ import annotations

import numpy as np

from ...errors import InputRangeError

NEAR_M, FAR_M = 0.1, 10.0
DIOPTER_SCALE_M = 0.7
ENCODINGS = ("minmax", "diopter")


def _clean(depth, invalid_as):
    d = np.asarray(depth, dtype=np.float64)
    return np.where(np.isnan(d) | (d <= 0), invalid_as, d)


def encode_depth(depth_m, encoding: str, *, stats: tuple[float, float] | None = None) -> np.ndarray:
    """Encoded depth, float32 of the same shape. ``stats``: minmax's (lo, hi)
    of the clamped depth taken from elsewhere (the whole image, for tiles);
    default: this array's own."""
    if encoding == "minmax":
        d = np.clip(_clean(depth_m, FAR_M), NEAR_M, FAR_M)
        lo, hi = minmax_stats(d) if stats is None else stats
        if hi - lo <= 1e-12:
            return np.zeros(d.shape, np.float32)
        return np.clip((d - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)
    if encoding == "diopter":
        d = np.maximum(_clean(depth_m, np.inf), NEAR_M)
        return (DIOPTER_SCALE_M / d).astype(np.float32)
    raise InputRangeError("depth encoding", encoding, " or ".join(ENCODINGS))


def minmax_stats(depth_m) -> tuple[float, float]:
    """(lo, hi) of the clamped depth (minmax's normalisation)."""
    d = np.clip(_clean(depth_m, FAR_M), NEAR_M, FAR_M)
    return float(d.min()), float(d.max())
