"""A camera's automatic exposure for rendered frames.

A render's linear values are radiance in arbitrary units: a lamp in the
frame or a bright wall can leave percent of the pixels above 1, where a
sensor clips and no correction can undo the bloom. Exposure is one gain on
the whole frame (shutter time and ISO), so scaling the render is exact.
The gain puts the mean luminance at a mid grey, as a camera's meter does,
but never so high that more than ``max_clipped`` of the pixels would pass
1.0.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import InputRangeError
from .statistics import LUMINANCE, clipped_fraction


@dataclass(frozen=True)
class ExposureOptions:
    """``mean_luminance``: the linear mean luminance the meter aims at
    (0.18: mid grey); ``max_clipped``: the largest share (0-1) of pixels
    whose brightest channel may pass 1.0 after the gain; ``max_gain``:
    the most a dark frame is brightened (a camera's longest exposure)."""
    mean_luminance: float = 0.18
    max_clipped: float = 0.003
    max_gain: float = 16.0

    def __post_init__(self):
        if not 0.0 < self.mean_luminance < 1.0:
            raise InputRangeError("exposure mean_luminance", self.mean_luminance, "0 < value < 1 (linear)")
        if not 0.0 <= self.max_clipped < 0.5:
            raise InputRangeError("exposure max_clipped", self.max_clipped, "0 <= share < 0.5")
        if not self.max_gain >= 1.0:
            raise InputRangeError("exposure max_gain", self.max_gain, ">= 1")

    def as_dict(self) -> dict:
        return asdict(self)


def exposure_gain(image: np.ndarray, options: ExposureOptions = ExposureOptions()) -> float:
    """The gain (> 0) for a linear (H, W, 3) frame: mean luminance to
    ``options.mean_luminance``, lowered until at most ``max_clipped`` of the
    pixels pass 1.0, at most ``max_gain``. A black frame gets 1."""
    img = np.asarray(image, np.float32)
    peak = img.max(axis=-1).ravel()
    mean = float(np.clip(img, 0.0, None).reshape(-1, 3).astype(np.float64).mean(axis=0) @ LUMINANCE)
    if not (mean > 0.0) or not np.isfinite(mean):
        return 1.0
    gain = min(options.mean_luminance / mean, options.max_gain)
    n_allowed = int(np.floor(options.max_clipped * peak.size))
    if n_allowed < peak.size:
        # the (n_allowed + 1)-th brightest pixel must stay at or below 1.0
        kth = float(np.partition(peak, peak.size - n_allowed - 1)[peak.size - n_allowed - 1])
        if kth > 0.0:
            gain = min(gain, 1.0 / kth)
    return float(gain)


def expose(image: np.ndarray, options: ExposureOptions = ExposureOptions()) -> tuple[np.ndarray, dict]:
    """(the frame times its gain, float32; a record: gain, clipped share
    before and after, mean luminance after)."""
    img = np.asarray(image, np.float32)
    gain = exposure_gain(img, options)
    out = (img * np.float32(gain)).astype(np.float32)
    mean = float(np.clip(out, 0.0, None).reshape(-1, 3).astype(np.float64).mean(axis=0) @ LUMINANCE)
    return out, {"gain": round(gain, 6), "clipped_before": round(clipped_fraction(img), 6),
                 "clipped": round(clipped_fraction(out), 6), "mean_luminance": round(mean, 6)}
