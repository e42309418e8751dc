"""Sensor noise: photon shot noise and read noise on a linear image.

Units: image values are linear, 1.0 = a full well (``full_well_electrons``
photo-electrons); read noise is in electrons (RMS). The noisy image comes
back in the same [0, 1] units, float32. Random numbers come from
``np.random.default_rng(seed)``: the same seed gives the same bytes (for the
same numpy, whose generators are stable across platforms).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import InputRangeError


def _number(name, v, *, lo, lo_open, unit):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v) \
            or v < lo or (lo_open and v == lo):
        raise InputRangeError(name, v, f"a finite number {'>' if lo_open else '>='} {lo:g} ({unit})")
    return float(v)


# beyond any sensor: the largest full wells are ~1e6 electrons; a read noise
# above the whole well leaves nothing but noise
MAX_FULL_WELL_ELECTRONS = 1e9
# numpy's Poisson sampler refuses a mean near 2^63; far below that, a pixel
# of more electrons than this is no exposure any sensor records
MAX_ELECTRONS = 1e15


def check_noise(full_well_electrons: float, read_noise_electrons: float) -> tuple[float, float]:
    """The noise settings checked (as :func:`add_sensor_noise` will): full
    well in (0, 1e9] electrons, read noise in [0, full well] electrons RMS."""
    fw = _number("full_well_electrons", full_well_electrons, lo=0.0, lo_open=True, unit="electrons")
    if fw > MAX_FULL_WELL_ELECTRONS:
        raise InputRangeError("full_well_electrons", fw, f"(0, {MAX_FULL_WELL_ELECTRONS:.0e}] electrons (real "
                              "sensors hold 1e3-1e6)")
    read = _number("read_noise_electrons", read_noise_electrons, lo=0.0, lo_open=False, unit="electrons RMS")
    if read > fw:
        raise InputRangeError("read_noise_electrons", read, f"[0, {fw:g}] electrons RMS, at most the full well "
                              "(beyond it the image is noise alone; real sensors: 1-10)")
    return fw, read


def add_sensor_noise(image, *, seed: int, full_well_electrons: float = 10000.0,
                     read_noise_electrons: float = 3.0, clip: bool = True) -> np.ndarray:
    """``image`` with shot and read noise, float32 of the same shape.

    Each value x (linear, 1.0 = full well) becomes
    ``(Poisson(x * full_well) + Normal(0, read_noise)) / full_well``, so its
    variance is ``(x * full_well + read_noise**2) / full_well**2``. Values
    above 1 are allowed in (they saturate when clipped). ``clip``: clip the
    result to [0, 1], as a sensor's well and ADC do (this biases the mean of
    values near 0 and 1 upwards / downwards). NaN, infinite or negative
    values raise InputRangeError."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputRangeError("seed", seed, "an integer >= 0")
    fw, read = check_noise(full_well_electrons, read_noise_electrons)
    x = np.asarray(image, dtype=np.float64)
    if not np.isfinite(x).all():
        raise InputRangeError("image", "NaN or infinite values", "finite linear values >= 0 (1.0 = full well)")
    if (x < 0).any():
        raise InputRangeError("image", float(x.min()), "finite linear values >= 0 (1.0 = full well)")
    top = float(x.max()) if x.size else 0.0
    if top * fw > MAX_ELECTRONS:       # checked before sampling: numpy's sampler would fail on it
        raise InputRangeError("image", top, f"linear values whose electrons (value x full well {fw:g}) stay "
                              f"<= {MAX_ELECTRONS:.0e}: at most {MAX_ELECTRONS / fw:.3g} here (1.0 = full well)")
    rng = np.random.default_rng(int(seed))
    # draw order fixed (shot, then read) so that a seed always means the same noise
    electrons = rng.poisson(x * fw).astype(np.float64)
    if read > 0:
        electrons += rng.normal(0.0, read, size=x.shape)
    out = electrons / fw
    if clip:
        np.clip(out, 0.0, 1.0, out=out)
    return out.astype(np.float32)
