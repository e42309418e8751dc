"""The noise a deconvolution must not amplify: a Poisson-Gaussian sensor
model, variance(x) = x / full_well + (read / full_well)^2 for a linear value
x in [0, 1], either given (the sensor model ``render.noise`` adds) or
estimated from the capture itself.

The estimate uses the finest diagonal Haar detail of each 2 x 2 block:
(a - b - c + d) / 2 has the noise's variance and almost none of a blurred
image's signal (a lens's blur removes the finest detail first). The detail's
squares are binned by the block's mean and a line a x + b is fitted to the
bins' medians (corrected for the median of a chi-square), robust to texture
that survives the blur.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputRangeError

# median of a chi-square with one degree of freedom: median(z^2) for z ~ N(0, 1)
_CHI2_MEDIAN = 0.454936


@dataclass(frozen=True)
class NoiseModel:
    """variance(x) = gain * x + floor (linear values; x clipped at 0)."""

    gain: float            # per unit of signal: 1 / full well (electrons)
    floor: float           # signal-independent: (read noise / full well)^2

    def __post_init__(self):
        for name in ("gain", "floor"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputRangeError(f"noise {name}", v, "a finite number >= 0")

    @classmethod
    def sensor(cls, full_well_electrons: float = 10000.0, read_noise_electrons: float = 3.0) -> "NoiseModel":
        """The model of ``render.noise.add_sensor_noise`` (electrons)."""
        if not (np.isfinite(full_well_electrons) and full_well_electrons > 0):
            raise InputRangeError("full well (electrons)", full_well_electrons, "> 0")
        if not (np.isfinite(read_noise_electrons) and read_noise_electrons >= 0):
            raise InputRangeError("read noise (electrons)", read_noise_electrons, ">= 0")
        return cls(1.0 / full_well_electrons, (read_noise_electrons / full_well_electrons) ** 2)

    def variance(self, x) -> np.ndarray:
        return self.gain * np.maximum(np.asarray(x, np.float64), 0.0) + self.floor


def estimate_noise(capture: np.ndarray, bins: int = 16, min_blocks: int = 64) -> NoiseModel:
    """A :class:`NoiseModel` fitted to a capture (H, W, C) linear: Haar
    diagonal details binned by brightness (all channels together)."""
    y = np.asarray(capture, np.float64)
    h, w = (y.shape[0] // 2) * 2, (y.shape[1] // 2) * 2
    if h < 4 or w < 4:
        raise InputRangeError("capture size for a noise estimate", y.shape[:2], "at least 4 x 4 pixels")
    b = y[:h, :w].reshape(h // 2, 2, w // 2, 2, -1)
    detail = (b[:, 0, :, 0] - b[:, 0, :, 1] - b[:, 1, :, 0] + b[:, 1, :, 1]) / 2.0
    mean = b.mean(axis=(1, 3))
    ok = (b.max(axis=(1, 3)) < 0.98) & (b.min(axis=(1, 3)) > 0.0)       # clipped blocks say nothing
    d2, mu = detail[ok] ** 2, mean[ok]
    if d2.size < min_blocks:
        return NoiseModel(0.0, 0.0)
    edges = np.quantile(mu, np.linspace(0, 1, bins + 1))
    xs, vs = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (mu >= lo) & (mu <= hi)
        if sel.sum() >= min_blocks // 4:
            xs.append(float(np.median(mu[sel])))
            vs.append(float(np.median(d2[sel])) / _CHI2_MEDIAN)
    if len(xs) < 2:
        return NoiseModel(0.0, float(np.median(d2) / _CHI2_MEDIAN))
    gain, floor = np.polyfit(xs, vs, 1)
    gain = max(float(gain), 0.0)
    floor = max(float(floor), 0.0) if gain > 0 else max(float(np.mean(vs)), 0.0)
    return NoiseModel(gain, floor)
