"""How accurately each resampling method warps an image, and how fast.

The test image is analytic, so the truth at any fractional position is
known: a sum of random plane waves, all below 0.7 x Nyquist (so the pixel
samples determine it), plus a smooth straight edge (tanh profile). It is
warped through a radial mapping like a lens's barrel distortion: the output
pixel at radius r shows the source at r (1 + k (r / r_corner)^2), k = -0.1
(10 % inward at the corners). Each method's warp is compared with the image
function evaluated at the source positions, over the source positions at
least ``_MARGIN`` pixels inside the frame (nearer the edge every method
sees the edge-repeated extension, not the function).

Run ``python -m lab resample-accuracy`` for the table.
"""
from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np

from dcdi_core.render.resample import METHODS, sample

_K = -0.1                 # relative radial shift at the corner
_WAVES = 12
_MAX_FREQ = 0.7           # of Nyquist (pi radians per pixel)
_EDGE_WIDTH_PX = 2.0      # tanh scale of the edge
_MARGIN = 8.0             # pixels between compared source positions and the frame


class WarpAccuracy(NamedTuple):
    method: str
    psnr_db: float        # peak 1 (the image spans [0.15, 0.85])
    max_abs_error: float
    ms: float | None      # best of `repeats` warps of a timing_shape image; None if not timed


def _test_function(seed: int, height: int, width: int):
    """f(y, x) -> values in [0.15, 0.85]; y, x in pixels of a (height, width) image."""
    rng = np.random.default_rng(seed)
    freq = np.pi * rng.uniform(0.1, _MAX_FREQ, _WAVES)        # radians per pixel
    angle = rng.uniform(0.0, np.pi, _WAVES)
    ky, kx = freq * np.sin(angle), freq * np.cos(angle)
    phase = rng.uniform(0.0, 2 * np.pi, _WAVES)
    amp = rng.uniform(0.5, 1.0, _WAVES)
    amp /= amp.sum()                                           # waves within [-1, 1]
    edge_dir = rng.uniform(0.0, 2 * np.pi)
    ey, ex = math.sin(edge_dir), math.cos(edge_dir)
    cy, cx = (height - 1) / 2, (width - 1) / 2

    def f(y, x):
        waves = np.zeros(np.broadcast(y, x).shape)
        for a, u, v, p in zip(amp, ky, kx, phase):
            waves += a * np.cos(u * y + v * x + p)
        edge = 0.5 * (1.0 + np.tanh(((y - cy) * ey + (x - cx) * ex) / _EDGE_WIDTH_PX))
        return 0.15 + 0.7 * (0.25 * (1.0 + waves) + 0.5 * edge)

    return f


def _source_positions(height: int, width: int):
    """Source (y, x) of every output pixel under the barrel-like mapping."""
    cy, cx = (height - 1) / 2, (width - 1) / 2
    dy = np.arange(height, dtype=np.float64)[:, None] - cy
    dx = np.arange(width, dtype=np.float64)[None, :] - cx
    scale = 1.0 + _K * (dy * dy + dx * dx) / (cy * cy + cx * cx)
    return cy + dy * scale, cx + dx * scale


def _best_ms(fn, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return 1000.0 * best


def warp_accuracy(height: int = 480, width: int = 720, seed: int = 0, methods=METHODS,
                  timing_shape: tuple[int, int, int] | None = (1280, 1920, 3),
                  repeats: int = 3) -> list[WarpAccuracy]:
    """One row per method: PSNR (dB, peak 1) and max |error| of the warp of
    the analytic test image (height x width pixels) against the function at
    the source positions, and the best of ``repeats`` timings (ms) of a
    warp of a ``timing_shape`` (H, W, C) image through the same mapping
    (None: not timed)."""
    f = _test_function(seed, height, width)
    img = f(*np.mgrid[0:height, 0:width].astype(np.float64))
    ys, xs = _source_positions(height, width)
    truth = f(ys, xs)
    inside = ((ys >= _MARGIN) & (ys <= height - 1 - _MARGIN)
              & (xs >= _MARGIN) & (xs <= width - 1 - _MARGIN))
    if timing_shape is not None:
        th, tw, tc = timing_shape
        timg = np.random.default_rng(seed).random((th, tw, tc), dtype=np.float32)
        tys, txs = _source_positions(th, tw)
    rows = []
    for m in methods:
        err = np.abs(sample(img, ys, xs, m) - truth)[inside]
        mse = float(np.mean(err * err))
        ms = None if timing_shape is None else _best_ms(lambda: sample(timg, tys, txs, m), repeats)
        rows.append(WarpAccuracy(m, math.inf if mse == 0 else 10 * math.log10(1.0 / mse), float(err.max()), ms))
    return rows


def format_warp_accuracy(rows) -> str:
    """The rows of :func:`warp_accuracy` as a Markdown table."""
    lines = ["| method | PSNR (dB) | max abs error | ms |", "|---|---:|---:|---:|"]
    for r in rows:
        ms = "-" if r.ms is None else f"{r.ms:.0f}"
        lines.append(f"| {r.method} | {r.psnr_db:.2f} | {r.max_abs_error:.2e} | {ms} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    p = argparse.ArgumentParser(prog="python -m lab resample-accuracy",
                                description="the warp's resampling methods: error and time (module docstring)")
    p.parse_args(argv)
    print(format_warp_accuracy(warp_accuracy()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
