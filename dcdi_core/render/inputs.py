"""Plausibility of an RGB-D input, checked before any work.

A depth map is metres (docs/design.md "Conventions"); NaN, 0 and negative values
are invalid (left sharp), ``inf`` and Blender's background (1e10) are
infinity. Two mistakes give garbage without these checks:

- a depth map in another unit (millimetres: every pixel lands beyond the
  library's far limit and gets the infinity PSF): warned about when more than
  half of the pixels are implausible (beyond 100 m but not the background, or
  invalid), with the unit the values suggest;
- a depth map with no valid pixel (the result would be the sharp image):
  refused (:class:`~dcdi_core.errors.RenderError`).

Negative pixel values in the image are warned about, not refused: light is
never negative, but renders and denoisers ring slightly below 0 at edges
(Cycles with Open Image Denoise, Lanczos resampling), and refusing those
images would refuse good data. The blur is linear, so they pass through it
as they are; the simulated output is clipped at 0 as always.
"""
from __future__ import annotations

import warnings

import numpy as np

from ..errors import RenderError

PLAUSIBLE_DEPTH_M = 100.0      # farther (finite, not the background) is suspect
BACKGROUND_M = 1.0e9           # at or beyond: a renderer's background value (Blender's 1e10), infinity
IMPLAUSIBLE_SHARE = 0.5        # warn when more than this share of the pixels is implausible


class InputWarning(UserWarning):
    """An input that is probably not what its maker meant (depths in another
    unit, negative light); the message says what was found."""


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %" if x >= 0.01 or x == 0 else f"{100 * x:.2g} %"


def depth_problems(depth, what: str = "the depth map") -> list[str]:
    """Warnings about ``depth`` (metres); raises RenderError when no pixel is
    valid. ``what`` names the file or argument in the messages."""
    d = np.asarray(depth, dtype=np.float64)
    n = d.size
    if n == 0:
        raise RenderError(f"{what}: the depth map has no pixel")
    valid = d > 0                                    # NaN, 0, negative: invalid
    n_valid = int(valid.sum())
    if n_valid == 0:
        finite = d[np.isfinite(d)]
        seen = (f"all {n} pixels are NaN" if finite.size == 0 else
                f"values from {finite.min():g} to {finite.max():g}, {_pct(1 - finite.size / n)} NaN")
        raise RenderError(f"{what}: no valid depth ({seen}); depths must be > 0 metres or inf (NaN, 0 and "
                          "negative values mark invalid pixels), so nothing would be simulated")
    far = valid & np.isfinite(d) & (d > PLAUSIBLE_DEPTH_M) & (d < BACKGROUND_M)
    n_far, n_bad = int(far.sum()), n - n_valid
    if (n_far + n_bad) / n <= IMPLAUSIBLE_SHARE:
        return []
    parts = []
    if n_far:
        med = float(np.median(d[far | (valid & np.isfinite(d) & (d < BACKGROUND_M))]))
        unit = (f"; its median {med:g} reads as {med / 1000:g} m in millimetres: the likely unit is mm "
                "(divide by 1000)" if 0.05 <= med / 1000 <= PLAUSIBLE_DEPTH_M else
                f" (median {med:g}): check its unit")
        parts.append(f"{_pct(n_far / n)} of the pixels lie beyond {PLAUSIBLE_DEPTH_M:g} m (they get the "
                     f"infinity PSF){unit}")
    if n_bad:
        parts.append(f"{_pct(n_bad / n)} of the pixels are invalid (NaN, 0 or negative: left sharp)")
    return [f"{what}: implausible depth map: " + "; ".join(parts) + "; depths are metres from the lens"]


def light_problems(image, what: str = "the image") -> list[str]:
    """Warnings about negative values in a linear-light image."""
    img = np.asarray(image)
    neg = img < 0
    if not neg.any():
        return []
    k = int(neg.any(axis=-1).sum()) if img.ndim == 3 else int(neg.sum())
    return [f"{what}: {k} pixel(s) ({_pct(k / max(1, img.shape[0] * img.shape[1]))}) hold negative values "
            f"(lowest {float(img.min()):.3g}); light is never negative: they are blurred as they are and the "
            "result is clipped at 0"]


def check_rgbd(image, depth, *, image_name: str = "the image", depth_name: str = "the depth map") -> None:
    """Refuse a depth map with no valid pixel; warn (InputWarning) about an
    implausible one and about negative light."""
    msgs = [] if depth is None else depth_problems(depth, depth_name)
    if image is not None:
        msgs += light_problems(image, image_name)
    for m in msgs:
        warnings.warn(m, InputWarning, stacklevel=3)


def depth_counts(depth, near_m: float) -> dict:
    """How many pixels of ``depth`` (metres) a job cannot use as they are:
    ``invalid_depth_pixels`` (NaN, 0 or negative: no depth) and
    ``near_clamped_pixels`` (valid but nearer than ``near_m``, the PSFs'
    near limit: blurred as at ``near_m``), with ``depth_pixels`` (all)."""
    d = np.asarray(depth, dtype=np.float64)
    valid = d > 0
    return {"depth_pixels": int(d.size), "invalid_depth_pixels": int((~valid).sum()),
            "near_clamped_pixels": int((valid & (d < near_m)).sum()), "near_limit_m": float(near_m)}


def depth_notes(counts: dict, what: str, invalid_fate: str) -> list[str]:
    """The lines a user is told about :func:`depth_counts`' pixels (none when
    every pixel is usable): the count and the share of each kind, and what
    the job did with them (``invalid_fate``)."""
    n = max(counts["depth_pixels"], 1)
    out = []
    k = counts["invalid_depth_pixels"]
    if k:
        out.append(f"{what}: {k} of {counts['depth_pixels']} pixels ({_pct(k / n)}) have no valid depth (NaN, 0 "
                   f"or negative): {invalid_fate}")
    k = counts["near_clamped_pixels"]
    if k:
        out.append(f"{what}: {k} of {counts['depth_pixels']} pixels ({_pct(k / n)}) are nearer than "
                   f"{counts['near_limit_m']:g} m, the PSFs' near limit: blurred as at {counts['near_limit_m']:g} m")
    return out
