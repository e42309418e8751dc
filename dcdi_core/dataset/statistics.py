"""What a data set's frames hold: texture energy, depth mix, clipping.

The measures `dcdi dataset stats` tabulates, one function each, so that a
recipe's author and the report measure alike. Images are float32 (H, W, 3)
linear light, depths float32 (H, W) metres (inf: background).
"""
from __future__ import annotations

import numpy as np

# depth bands of the report, metres: [lo, hi)
DEPTH_BANDS_M = ((0.7, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, np.inf))
HIGH_FREQUENCY_CYCLES_PER_PX = 0.1
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)     # Rec. 709, linear light


def spectral_energy(image: np.ndarray, cutoff_cycles_per_px: float = HIGH_FREQUENCY_CYCLES_PER_PX
                    ) -> tuple[float, float]:
    """(energy above the cutoff, total energy) of the image's luminance
    spectrum: linear RGB clipped to [0, 1], Rec. 709 luminance, mean
    removed, a 2-D Hann window (so the frame's border adds no false high
    frequencies), |FFT|^2 summed over radial frequencies above the cutoff
    (cycles per pixel) and over all of them. Sum these over frames to pool."""
    y = np.clip(np.asarray(image, np.float64), 0.0, 1.0) @ LUMINANCE
    h, w = y.shape
    window = np.hanning(h)[:, None] * np.hanning(w)[None, :]
    y = (y - (y * window).sum() / window.sum()) * window
    power = np.abs(np.fft.rfft2(y)) ** 2
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    # rfft keeps one half of the spectrum: the columns 1 .. W/2 - 1 stand for two bins each
    weight = np.full(power.shape[1], 2.0)
    weight[0] = 1.0
    if w % 2 == 0:
        weight[-1] = 1.0
    power = power * weight[None, :]
    high = power[np.hypot(fy, fx) > cutoff_cycles_per_px].sum()
    return float(high), float(power.sum())


def high_frequency_share(image: np.ndarray, cutoff_cycles_per_px: float = HIGH_FREQUENCY_CYCLES_PER_PX) -> float:
    """Share (0-1) of the image's spectral energy above the cutoff
    (:func:`spectral_energy`); 0 for a flat image."""
    high, total = spectral_energy(image, cutoff_cycles_per_px)
    return high / total if total > 0 else 0.0


def depth_band_counts(depth_m: np.ndarray, bands=DEPTH_BANDS_M) -> np.ndarray:
    """Pixels per band [lo, hi) metres; infinite depth counts in a band whose
    upper end is inf; invalid depths (NaN, <= 0) and depths below the first
    band count in none."""
    d = np.asarray(depth_m, np.float64)
    return np.array([int(np.count_nonzero((d >= lo) & ((d < hi) | (np.isinf(hi) & np.isinf(d)))))
                     for lo, hi in bands], dtype=np.int64)


def clipped_mask(image: np.ndarray, level: float = 1.0) -> np.ndarray:
    """Pixels whose brightest channel exceeds ``level`` (linear): what a
    sensor clips."""
    return np.asarray(image).max(axis=-1) > level


def clipped_fraction(image: np.ndarray, level: float = 1.0) -> float:
    """Share (0-1) of pixels whose brightest channel exceeds ``level``."""
    return float(clipped_mask(image, level).mean())
