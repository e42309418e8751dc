"""Geometric distortion of a lens from its real chief rays, and image warps.

The lens maps an object at field angle theta (p = tan theta, seen from the
paraxial entrance pupil) to the height where its real chief ray meets the
sensor, ``h_real``; an ideal pinhole camera with the same focal length puts
it at the paraxial height ``h_ideal`` (proportional to p). A render from
Blender's pinhole camera is such an ideal image: :func:`distort` warps it
into what the lens records, :func:`undistort` does the reverse.

Conventions: heights in mm on the sensor, radial (the lens is rotationally
symmetric, so a point keeps its azimuth), chief rays at the lens's design
wavelength (lateral colour belongs to the PSFs, which are centred on the
design-wavelength chief ray). The object is at infinity: the depth
dependence is ignored. For MOS-S1 and MOS-S2 (stop in front of the lens,
entrance pupil at the stop) the real chief ray of a given p is the same ray
at any depth, so h_real at 0.7 m equals h_real at infinity (measured: equal
to 4e-15 mm up to field 1); for 6P, whose stop is inside the lens, the two
differ by at most 2.4e-4 mm (0.02 px of 12.2 um) up to field 1.
:func:`depth_dependence_mm` measures it for any lens.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..optics.aiming import aim_chief, chief_ray_sensor_y, solve_field
from ..errors import InputRangeError
from ..optics.errors import OpticsError
from ..optics.paraxial import paraxial_image_height_mm
from .geometry import ImageGeometry
from .resample import METHODS, sample

# what a warp may resample an image with (resample.METHODS)
INTERPOLATIONS = METHODS


def check_interpolation(name: str) -> str:
    """The interpolation's name if it is one of INTERPOLATIONS, else InputRangeError."""
    if name not in INTERPOLATIONS:
        raise InputRangeError("interpolation", name, "one of " + ", ".join(INTERPOLATIONS))
    return name


# largest field angle the fallback search considers (degrees)
_MAX_ANGLE_DEG = 89.0


@dataclass(frozen=True)
class RadialDistortion:
    """Real chief-ray height ``real_mm`` (mm) against the ideal (paraxial,
    undistorted) height ``ideal_mm`` (mm) of the same object direction,
    tabulated on a fine grid (uniform in ideal height) for an object at
    infinity. Both columns start at 0 and increase strictly.

    The depth dependence is ignored (see the module docstring: none for
    MOS-S1, at most 0.02 px of 12.2 um for 6P between 0.7 m and
    infinity)."""

    ideal_mm: np.ndarray
    real_mm: np.ndarray
    lens_id: str = ""

    def __post_init__(self):
        i = np.asarray(self.ideal_mm, dtype=np.float64)
        r = np.asarray(self.real_mm, dtype=np.float64)
        if i.shape != r.shape or i.ndim != 1 or i.size < 2:
            raise InputRangeError("distortion table", (i.shape, r.shape), "two 1-D arrays of equal length >= 2")
        if i[0] != 0.0 or r[0] != 0.0:
            raise InputRangeError("distortion table", (float(i[0]), float(r[0])), "both columns starting at 0")
        if not (np.all(np.diff(i) > 0) and np.all(np.diff(r) > 0)):
            raise OpticsError(f"lens {self.lens_id or '?'}: the real chief-ray height is not monotonic in the "
                              "ideal height, so the distortion cannot be inverted")
        object.__setattr__(self, "ideal_mm", i)
        object.__setattr__(self, "real_mm", r)

    @property
    def reach_ideal_mm(self) -> float:
        return float(self.ideal_mm[-1])

    @property
    def reach_real_mm(self) -> float:
        return float(self.real_mm[-1])

    @staticmethod
    def _lookup(h, x, y):
        # radial heights are odd functions: sign(h) f(|h|); NaN beyond the table
        h = np.asarray(h, dtype=np.float64)
        a = np.abs(h)
        out = np.sign(h) * np.interp(a, x, y)
        return np.where(a <= x[-1], out, np.nan)

    def real_from_ideal(self, h) -> np.ndarray:
        """Real height (mm) of the object direction imaged ideally at ``h`` (mm);
        NaN beyond the table."""
        return self._lookup(h, self.ideal_mm, self.real_mm)

    def ideal_from_real(self, h) -> np.ndarray:
        """Ideal height (mm) of the object direction whose real chief ray lands
        at ``h`` (mm); NaN beyond the table."""
        return self._lookup(h, self.real_mm, self.ideal_mm)

    def relative(self, ideal_mm) -> np.ndarray:
        """Relative distortion real / ideal - 1 at ideal heights (mm); 0 on the axis."""
        h = np.asarray(ideal_mm, dtype=np.float64)
        r = self.real_from_ideal(h)
        safe = np.where(h != 0, h, 1.0)
        return np.where(h != 0, r / safe - 1.0, 0.0)


def _chief_heights(lens, p, depth_mm=math.inf):
    p = np.asarray(p, dtype=np.float64)
    a = aim_chief(lens, np.full(p.shape, depth_mm), p)
    h, ok = chief_ray_sensor_y(lens, a)
    return h, ok


def _largest_reaching_p(lens, p_hi: float) -> float:
    """Largest p in (0, p_hi] up to which every chief ray reaches the sensor."""
    p = np.tan(np.radians(np.linspace(0.0, math.degrees(math.atan(p_hi)), 513)))
    _, ok = _chief_heights(lens, p)
    bad = np.flatnonzero(~ok)
    if bad.size == 0:
        return p_hi
    if bad[0] <= 1:
        raise OpticsError(f"lens {lens.id} ({lens.path}): no real chief ray reaches the sensor even "
                          f"at {math.degrees(math.atan(p[1])):.3g} degrees off axis")
    lo, hi = p[bad[0] - 1], p[bad[0]]
    for _ in range(40):           # bisection to ~1e-12 of the interval
        mid = 0.5 * (lo + hi)
        if _chief_heights(lens, [mid])[1][0]:
            lo = mid
        else:
            hi = mid
    return float(lo)


def radial_distortion(lens, max_field: float = 1.5, n: int = 257) -> RadialDistortion:
    """The lens's distortion table from real chief rays (object at infinity).

    Samples object directions (n uniform in p = tan(angle) and n uniform in
    angle, merged) from the axis up to where the real chief ray lands at
    ``max_field`` x the sensor semi-diagonal or, if it never gets there, up
    to the largest angle whose chief ray still reaches the sensor; beyond
    field 1 the table also stops where the real height stops increasing or
    a chief ray fails. The ideal height is the paraxial one,
    ``paraxial_image_height_mm``, at the same angle. With the defaults the
    tables of the paper lenses interpolate to 1.6e-4 mm (0.013 px of
    12.2 um) or better.

    Raises OpticsError naming the lens if the real height folds back, or a
    chief ray fails, inside field 1 (such an image cannot be warped
    radially)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputRangeError("n", n, "an integer >= 2")
    if not (isinstance(max_field, (int, float, np.integer, np.floating)) and math.isfinite(max_field)
            and max_field > 0):
        raise InputRangeError("max_field", max_field, "a finite number > 0 (1 = sensor semi-diagonal)")
    sd = lens.sensor.semi_diagonal_mm
    a = solve_field(lens, np.array([math.inf]), np.array([max_field * sd]))
    if a.ok[0] and a.p[0] > 0:
        p_max = float(a.p[0])
    else:
        p_max = _largest_reaching_p(lens, math.tan(math.radians(_MAX_ANGLE_DEG)))
    # n directions uniform in p (uniform in ideal height: the finest where the
    # ideal height grows fastest against the real one) merged with n uniform
    # in angle (which keeps small fields finely sampled when p_max is huge)
    p = np.union1d(np.linspace(0.0, p_max, int(n)), np.tan(np.linspace(0.0, math.atan(p_max), int(n))))
    p = p[np.concatenate([[True], np.diff(p) > 1e-12 * p_max])]
    p = np.minimum(p, p_max)
    real, ok = _chief_heights(lens, p)
    if not ok.all():
        # near the largest reaching angle aiming is marginal: keep the rays
        # before the first failure if they already reach beyond field 1
        k = int(np.flatnonzero(~ok)[0])
        if k < 2 or real[k - 1] <= sd:
            raise OpticsError(f"lens {lens.id} ({lens.path}): the chief ray at "
                              f"{math.degrees(math.atan(p[k])):.4g} degrees does not reach the sensor, "
                              "though a wider one does: the distortion table has a hole inside field 1")
        p, real = p[:k], real[:k]
    ideal = paraxial_image_height_mm(lens, np.degrees(np.arctan(p)))
    real[0] = ideal[0] = 0.0               # the axial chief ray, exactly
    if not (ideal[1] > 0):
        raise OpticsError(f"lens {lens.id} ({lens.path}): the paraxial image height is not positive "
                          f"({ideal[1]:.4g} mm): the lens forms no real, inverted image on its sensor")
    steps = np.diff(real) > 0
    if not steps.all():
        k = int(np.flatnonzero(~steps)[0])          # real[k + 1] <= real[k]
        if real[k] <= sd:
            raise OpticsError(
                f"lens {lens.id} ({lens.path}): the real chief-ray height stops increasing at "
                f"{real[k]:.4g} mm (field {real[k] / sd:.3g}, {math.degrees(math.atan(p[k])):.4g} degrees), "
                "inside the sensor: the distortion folds the image and cannot be warped radially")
        real, ideal = real[:k + 1], ideal[:k + 1]   # keep the monotonic part, beyond field 1
    return RadialDistortion(ideal, real, lens.id)


def depth_dependence_mm(lens, depth_m: float, fields=None) -> np.ndarray:
    """|h_real(p, depth) - h_real(p, inf)| (mm) for the object directions p that
    land at ``fields`` (default 0..1) from infinity: how much the distortion
    of an object at ``depth_m`` metres differs from the table's."""
    f = np.linspace(0.0, 1.0, 21) if fields is None else np.atleast_1d(np.asarray(fields, float))
    a = solve_field(lens, np.full(f.shape, math.inf), f * lens.sensor.semi_diagonal_mm)
    h_inf, ok_inf = chief_ray_sensor_y(lens, a)
    h_d, ok_d = _chief_heights(lens, a.p, float(depth_m) * 1000.0)
    return np.where(a.ok & ok_inf & ok_d, np.abs(h_d - h_inf), np.nan)


# ------------------------------------------------------------------- warps
def _check_image(image, geometry: ImageGeometry, name: str) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[:2] != (geometry.height, geometry.width):
        raise InputRangeError(f"{name} shape", img.shape,
                              f"({geometry.height}, {geometry.width}) or ({geometry.height}, "
                              f"{geometry.width}, C), as its geometry says")
    return img


def _source_positions(geometry: ImageGeometry, source_geometry: ImageGeometry, source_radius, reach_mm: float,
                      what: str = "the sensor", table_name: str = "real-height"):
    """(y, x, valid): where in the input (its pixel coordinates) each output
    pixel at sensor radius r looks, at radius source_radius(r) and the same
    azimuth; valid where that lies on the input's pixel footprint."""
    rows = np.arange(geometry.height, dtype=np.float64)[:, None]
    cols = np.arange(geometry.width, dtype=np.float64)[None, :]
    dy = (rows - geometry.center_px[0]) * geometry.pixel_pitch_mm
    dx = (cols - geometry.center_px[1]) * geometry.pixel_pitch_mm
    r = np.hypot(dy, dx)
    if r.max() > reach_mm:
        raise InputRangeError(
            "image field", round(float(r.max()) / geometry.semi_diagonal_mm, 6),
            f"<= {reach_mm / geometry.semi_diagonal_mm:.4g}, the reach of the {table_name} table for "
            f"{what} (compute it with radial_distortion(lens, max_field=...) larger, or check the pixel pitch)")
    rs = source_radius(r)
    # on the axis the warp's scale is its slope at 0, which is 1 for ideal vs real
    scale = np.where(r > 0, rs / np.where(r > 0, r, 1.0), 1.0)
    y = source_geometry.center_px[0] + dy * scale / source_geometry.pixel_pitch_mm
    x = source_geometry.center_px[1] + dx * scale / source_geometry.pixel_pitch_mm
    # valid: the source position lies on the input's pixel footprint (half a
    # pixel beyond the outer pixel centres, where the edge pixel is repeated)
    valid = ((y >= -0.5) & (y <= source_geometry.height - 0.5)
             & (x >= -0.5) & (x <= source_geometry.width - 0.5))
    return y, x, valid


def _warp(image, geometry: ImageGeometry, source_geometry: ImageGeometry, source_radius, what: str,
          reach_mm: float, table_name: str, interpolation: str = "linear"):
    """Output pixel at sensor radius r (output geometry) shows the input at
    radius source_radius(r) (input geometry), same azimuth, sampled with
    ``resample.sample(..., method=interpolation)``."""
    check_interpolation(interpolation)
    img = _check_image(image, source_geometry, "image")
    y, x, valid = _source_positions(geometry, source_geometry, source_radius, reach_mm, what, table_name)
    out = sample(img, y, x, interpolation)
    out *= (valid[..., None] if out.ndim == 3 else valid).astype(np.float32)
    return out, valid


def distort(image, lens, geometry: ImageGeometry, *, distortion: RadialDistortion | None = None,
            source_geometry: ImageGeometry | None = None, return_mask: bool = False,
            interpolation: str = "linear"):
    """Warp an ideal (pinhole, all-in-focus) image into what the lens records.

    The output pixel at sensor radius r (mm) shows the input at ideal radius
    ``ideal_from_real(r)``, same azimuth, sampled with ``interpolation``
    (one of ``resample.METHODS``: "nearest" for depth maps, "linear",
    "keys", "lanczos3", "bspline"; see :mod:`.resample`). ``image``
    (H, W) or (H, W, C); output float32 of the same shape. Output pixels whose
    source falls outside the input are 0 (black): with barrel distortion
    the corners need content from beyond the ideal image's frame. To avoid
    them, render the ideal image larger (over-scan) and describe it with
    ``source_geometry`` (same pitch, larger size, for instance); ``geometry``
    is then the output's.

    return_mask: also return ``valid`` (H, W) bool, True where the output
    pixel's source lies inside the input."""
    d = distortion or radial_distortion(lens)
    src = source_geometry or geometry
    out, valid = _warp(image, geometry, src, d.ideal_from_real, "distort()", d.reach_real_mm, "real-height",
                       interpolation)
    return (out, valid) if return_mask else out


def undistort(image, lens, geometry: ImageGeometry, *, distortion: RadialDistortion | None = None,
              source_geometry: ImageGeometry | None = None, return_mask: bool = False,
              interpolation: str = "linear"):
    """The inverse of :func:`distort`: a recorded image back to the ideal
    (pinhole) geometry. The output pixel at ideal radius r (mm) shows the
    input at real radius ``real_from_ideal(r)``. Arguments as :func:`distort`
    (``source_geometry``: the recorded image's geometry if it differs)."""
    d = distortion or radial_distortion(lens)
    src = source_geometry or geometry
    out, valid = _warp(image, geometry, src, d.real_from_ideal, "undistort()", d.reach_ideal_mm, "ideal-height",
                       interpolation)
    return (out, valid) if return_mask else out
