"""Kernels at another pixel pitch: exact area resampling (numpy only).

A PSF kernel of this engine is a pixel histogram (``psf.deposit``): value
[i, j] is the energy that lands in the square pixel (i, j) of side ``p0``
mm, the centre pixel (k // 2, k // 2) centred on the kernel origin (the
chief ray). Read as a density that is constant over each pixel, its
integral over any square of side ``p`` is exact; for pixels of the new
pitch, centred on the same origin, that integral is

    K_new = A_y K_old A_x^T,   A[j, i] = overlap(new pixel j, old pixel i) / p0

(separable because the pixels are axis-aligned squares: the overlap of two
squares is the product of the overlaps of their sides; A's columns sum to 1
where the new pixels cover the old kernel, so the sum is kept and nothing
turns negative).

Only downsampling (``p >= p0``) is served: going finer would spread each old
pixel's energy evenly over the new pixels inside it, detail the histogram
never held. A ratio ``p / p0`` that is an odd integer puts every new pixel
edge on an old one, and the result is then the histogram the same rays
would have made at pitch ``p`` (up to the rays outside the old kernel).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import InputRangeError

# pitches within this relative tolerance are the same (no resampling): the
# edge of a 129 px kernel moves by less than 0.007 px; a 1280 x 1920 image
# spanning the paper lenses' sensor diagonal (12.19988 um) is their stated
# 12.2 um sensor
PITCH_RTOL = 1e-4

# The other pixel-pitch tolerances, each for its own question (relative):
# one pitch given twice (a library or PSF settings opened for this image) is the same number
SAME_GIVEN_RTOL = 1e-9
# a depth refinement's learned scene statistics hold at the pitch it learned, within 1 %
REFINEMENT_PITCH_RTOL = 0.01
# a correction network's learned blur size holds within 5 % of the pitch it learned
NETWORK_PITCH_RTOL = 0.05


def learned_pitch_holds(image_mm: float, learned_mm: float, rtol: float) -> bool:
    """Whether an image's pixel pitch is the one a file learned: |image / learned - 1| <= ``rtol``."""
    return abs(image_mm / learned_mm - 1) <= rtol


def check_downsampling(pitch_from_mm: float, pitch_to_mm: float, what: str = "pixel pitch") -> None:
    """Refuse a resampling that is not a downsampling: ``pitch_to_mm`` must be
    >= ``pitch_from_mm`` (both > 0 mm). ``what`` names the request in the error."""
    for name, v in (("pitch the kernels hold", pitch_from_mm), (what, pitch_to_mm)):
        if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
            raise InputRangeError(name, v, "> 0 mm")
    if pitch_to_mm < pitch_from_mm * (1.0 - PITCH_RTOL):
        raise InputRangeError(what, pitch_to_mm,
                              f">= {pitch_from_mm:.6g} mm, the pitch the kernels hold (area resampling only "
                              "downsamples: a finer pitch would invent detail the pixel histogram never held)")


def same_pitch(a_mm: float, b_mm: float) -> bool:
    """True if two pitches are equal within ``PITCH_RTOL``."""
    return math.isclose(a_mm, b_mm, rel_tol=PITCH_RTOL)


def resampled_size(k: int, pitch_from_mm: float, pitch_to_mm: float) -> int:
    """Smallest odd kernel size at ``pitch_to_mm`` whose square covers a
    k x k kernel at ``pitch_from_mm`` (both centred on the origin): k when the
    pitches are the same."""
    if not (isinstance(k, (int, np.integer)) and k >= 1 and k % 2 == 1):
        raise InputRangeError("kernel size", k, "an odd integer >= 1")
    check_downsampling(pitch_from_mm, pitch_to_mm)
    if same_pitch(pitch_from_mm, pitch_to_mm):
        return int(k)
    n = math.ceil(k * pitch_from_mm / pitch_to_mm - 1e-9)
    return int(n if n % 2 == 1 else n + 1)


def overlap_matrix(k_from: int, pitch_from_mm: float, k_to: int, pitch_to_mm: float) -> np.ndarray:
    """A (k_to, k_from) float64: the length of old pixel i inside new pixel j
    over the old pitch (the fraction of old pixel i that new pixel j takes),
    both rows of pixels centred on 0."""
    def edges(k, p):
        c = (np.arange(k) - k // 2) * p
        return c - 0.5 * p, c + 0.5 * p
    lo_n, hi_n = edges(k_to, pitch_to_mm)
    lo_o, hi_o = edges(k_from, pitch_from_mm)
    length = np.minimum(hi_n[:, None], hi_o[None, :]) - np.maximum(lo_n[:, None], lo_o[None, :])
    return np.maximum(length, 0.0) / pitch_from_mm


def area_resample(kernels, pitch_from_mm: float, pitch_to_mm: float, k_to: int | None = None) -> np.ndarray:
    """Kernels (..., k, k) at ``pitch_from_mm`` as kernels (..., k_to, k_to)
    at ``pitch_to_mm`` (mm; >= ``pitch_from_mm``): each new pixel the integral
    of the piecewise-constant old kernel over its square. ``k_to`` (odd;
    default :func:`resampled_size`, which keeps every kernel's sum) may be
    smaller, cropping. Returns (and computes in) float32 for float32 input, else float64."""
    a = np.asarray(kernels)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise InputRangeError("kernels shape", a.shape, "(..., k, k) square kernels")
    k = a.shape[-1]
    if k_to is None:
        k_to = resampled_size(k, pitch_from_mm, pitch_to_mm)
    else:
        check_downsampling(pitch_from_mm, pitch_to_mm)
        if not (isinstance(k_to, (int, np.integer)) and k_to >= 1 and k_to % 2 == 1):
            raise InputRangeError("k_to (resampled kernel size)", k_to, "an odd integer >= 1")
    if same_pitch(pitch_from_mm, pitch_to_mm) and k_to == k:
        return a.copy()
    w = overlap_matrix(k, pitch_from_mm, int(k_to), pitch_to_mm)
    # float32 kernels are resampled in float32 (rounding ~1e-7 of a kernel's peak, the kernels' own
    # precision): twice as fast as float64 and half the memory for the OLF's thousands of kernels
    dtype = np.float32 if a.dtype == np.float32 else np.float64
    w = w.astype(dtype)
    return w @ a.astype(dtype, copy=False) @ w.T      # matmul broadcasts over the leading axes


__all__ = ["area_resample", "overlap_matrix", "resampled_size", "check_downsampling", "same_pitch", "PITCH_RTOL",
           "SAME_GIVEN_RTOL", "REFINEMENT_PITCH_RTOL", "NETWORK_PITCH_RTOL", "learned_pitch_holds"]
