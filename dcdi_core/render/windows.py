"""The overlapping windows of a patch-wise convolution: each m x m patch is
convolved over an (m + 2b)^2 window and blended with its neighbours by a
separable ramp that sums to one (shared by the reference windows method,
``render.convolve``, and the fast one, ``render.convolve_fast``). Sizes in
pixels."""
from __future__ import annotations

import math

import numpy as np


def blend_window(m: int, b: int) -> np.ndarray:
    """The 1-D weights (m + 2b,) of a patch over pixels [i m - b, (i + 1) m + b):
    1 inside, linear ramps 2b wide across each border, so that neighbouring
    windows sum to 1. b = m/2 is the tent (bilinear blend of patch results)."""
    x = np.arange(m + 2 * b) + 0.5 - b                  # pixel centre relative to the patch's first pixel
    rise = np.clip((x + b) / (2 * b), 0.0, 1.0)
    fall = np.clip((m + b - x) / (2 * b), 0.0, 1.0)
    return np.minimum(rise, fall)


def live_windows(padded: np.ndarray, m: int, b: int, r: int) -> np.ndarray:
    """(qh, qw) bool: windows whose input (padded patches up to ceil((b + r) / m)
    away) is not all zero (a depth layer's empty part gives zero: skipped)."""
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    return grow_square(padded.reshape(qh, m, qw, m, -1).any(axis=(1, 3, 4)), math.ceil((b + r) / m))


def grow_square(mask: np.ndarray, n: int) -> np.ndarray:
    """(h, w) bool ``mask`` dilated by a (2n + 1)^2 square (cells within n
    rows and n columns of a True cell), as a row pass then a column pass."""
    out = mask.copy()
    for axis in (0, 1):
        src = out.copy()
        for s in range(1, min(n, out.shape[axis] - 1) + 1):
            ahead = [slice(None)] * 2
            behind = [slice(None)] * 2
            ahead[axis], behind[axis] = slice(s, None), slice(None, -s)
            out[tuple(ahead)] |= src[tuple(behind)]
            out[tuple(behind)] |= src[tuple(ahead)]
    return out
