"""The iris: a lens stopped down to an f-number, with round or bladed stops.

A photographer sets the depth of field with the f-number N = EFL / D, D the
entrance pupil's diameter. The pupil is the image of the stop through the
surfaces in front of it, so (paraxially, exactly) it scales with the stop's
semi-diameter: stopping a lens of wide-open F-number N0 down to N scales
its stop by N0 / N. Every other surface keeps its clear aperture as traced,
so the cat's-eye vignetting off axis of a lens wide open fades as it is
stopped down, as it does on a real lens.

Blades: a real iris is a polygon. ``blades`` n >= 3 makes the stop a regular
n-gon inscribed in the stop's circle (its corners on the circle; the
f-number names that circle, as lens makers do), one corner at
``rotation_deg`` from +y towards +x, seen from the object side. The tracer
vignettes rays outside it and the pupil samples fill it, so a defocused PSF
takes the polygon's shape (turned by 180 degrees between a point in front of
the focus and one behind it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputRangeError

MAX_F_NUMBER = 128.0        # f/128: beyond it diffraction, not the geometry, is the PSF
MIN_BLADES, MAX_BLADES = 3, 32     # a triangle is the fewest; beyond 32 a polygon is a circle within 0.5 %
OPEN_TOLERANCE = 1e-3       # an f-number within 0.1 % of the wide-open one is the lens wide open


@dataclass(frozen=True)
class Aperture:
    """The iris asked for: ``f_number`` (None: wide open), ``blades`` (0
    round, or 3-32) and ``rotation_deg`` (a corner's angle from +y, degrees),
    checked when made."""

    f_number: float | None = None
    blades: int = 0
    rotation_deg: float = 0.0

    def __post_init__(self):
        n = self.f_number
        if n is not None and (isinstance(n, bool) or not isinstance(n, (int, float, np.floating))
                              or not (math.isfinite(n) and 0.0 < n <= MAX_F_NUMBER)):
            raise InputRangeError("f-number", n, f"a number in (0, {MAX_F_NUMBER:g}] (or none: wide open)")
        b = self.blades
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not (
                b == 0 or MIN_BLADES <= b <= MAX_BLADES):
            raise InputRangeError("blades", b, f"0 (round) or an integer in [{MIN_BLADES}, {MAX_BLADES}]")
        r = self.rotation_deg
        if isinstance(r, bool) or not isinstance(r, (int, float, np.floating)) or not math.isfinite(r) \
                or abs(r) > 360.0:
            raise InputRangeError("blade rotation", r, "degrees in [-360, 360]")

    @property
    def is_lens_as_designed(self) -> bool:
        """Nothing asked: the lens wide open with its round stop."""
        return self.f_number is None and self.blades == 0

    def describe(self, f_number: float) -> str:
        """'f/8, 6 blades' (the stop as made), 'f/8, 6 blades turned 15 deg'
        where the blades are turned (the name, and every key made of it,
        tells two turns apart)."""
        turned = f" turned {self.rotation_deg:.4g} deg" if self.blades and self.rotation_deg else ""
        return f"f/{f_number:.3g}" + (f", {self.blades} blades{turned}" if self.blades else "")


def wide_open_f_number(lens) -> float:
    """The lens's paraxial F-number as prescribed (EFL / entrance pupil, object at infinity)."""
    from .paraxial import first_order
    return float(first_order(lens).f_number)


def stopped_down(lens, aperture: Aperture):
    """``lens`` with its stop closed to ``aperture.f_number`` (a wider one than
    the lens's own is refused) and shaped by its blades; the lens itself when
    nothing is asked. The new lens's name says its iris; its fingerprint (and
    so every PSF cache and store check) differs from the lens wide open."""
    if not isinstance(aperture, Aperture):
        raise InputRangeError("aperture", aperture, "an Aperture")
    if aperture.is_lens_as_designed:
        return lens
    n0 = wide_open_f_number(lens)
    n = n0 if aperture.f_number is None else float(aperture.f_number)
    if n < n0 * (1.0 - OPEN_TOLERANCE):
        raise InputRangeError(f"f-number of {lens.id} ({lens.path})", n,
                              f"f/{n0:.3g} (its widest: the stop as prescribed) to f/{MAX_F_NUMBER:g}")
    n = max(n, n0)
    i = lens.stop_index
    stop = lens.surfaces[i]
    new_stop = replace(stop, semi_diameter_mm=stop.semi_diameter_mm * n0 / n, blades=int(aperture.blades),
                       blade_rotation_deg=float(aperture.rotation_deg) if aperture.blades else 0.0)
    surfaces = lens.surfaces[:i] + (new_stop,) + lens.surfaces[i + 1:]
    iris = aperture.describe(n)
    return replace(lens, surfaces=surfaces, name=f"{lens.name} at {iris}", content_hash="", iris=iris)


def inside_iris(x, y, blades: int, rotation_deg: float, radius_mm: float) -> np.ndarray:
    """(...) bool: the points (x, y) mm inside the regular ``blades``-gon
    inscribed in the circle of ``radius_mm`` (a corner at ``rotation_deg``
    from +y towards +x). A point is inside when its projection on every
    edge's outward normal is at most the apothem R cos(pi / n)."""
    n = int(blades)
    apothem = radius_mm * math.cos(math.pi / n)
    # the edges' normals bisect neighbouring corners: corner k at rot + 2 pi k / n (from +y)
    inside = np.ones(np.shape(x), bool)
    for k in range(n):
        a = math.radians(rotation_deg) + (2 * k + 1) * math.pi / n
        inside &= x * math.sin(a) + y * math.cos(a) <= apothem
    return inside
