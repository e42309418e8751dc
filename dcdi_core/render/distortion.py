"""Geometric distortion of a lens from its real chief rays, and image warps.

The lens maps an object at field angle theta (p = tan theta, seen from the
paraxial entrance pupil) at depth d to the height where its real chief ray
meets the sensor, ``h_real(p, d)``; an ideal pinhole camera with the same
focal length puts it at the paraxial height ``h_ideal`` (proportional to p,
whatever the depth). A render from Blender's pinhole camera is such an
ideal image: :func:`distort` warps it into what the lens records,
:func:`undistort` does the reverse.

Two tables. :class:`ChiefRayMap` (what the renderers use): ``h_real`` at
the sensor where the focus puts it, per depth (uniform in diopters), so
that refocusing breathes as the lens does (the sensor moves back, the
image grows: 4.8 % at the corner for a 50 mm Sonnar from infinity to 1.5
m) and the distortion follows each pixel's depth (pupil aberration: none
for MOS-S1 and MOS-S2, whose entrance pupil is the stop in front; at most
0.02 px of 12.2 um for 6P; 0.54 px of 100 um at the Sonnar's corner
between 1.5 and 6 m). :class:`RadialDistortion`: one depth's table (by default objects
at infinity with the prescription's sensor), for the warps below and the
lens's reports; :func:`depth_dependence_mm` measures how far a depth's
table is from it.

Conventions: heights in mm on the sensor, radial (the lens is rotationally
symmetric, so a point keeps its azimuth), chief rays at the lens's design
wavelength (lateral colour belongs to the PSFs, which are centred on the
design-wavelength chief ray), depths in metres from the first vertex.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..optics.aiming import aim_chief, chief_ray_sensor_y, solve_field
from .. import caches
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
    tabulated on a fine grid (uniform in ideal height) for one depth (by
    default an object at infinity). Both columns start at 0 and increase
    strictly. The renderers use a :class:`ChiefRayMap` (every depth, the
    focused sensor)."""

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
    a = aim_chief(lens, np.broadcast_to(np.asarray(depth_mm, np.float64), p.shape), p)
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


def _p_max(lens, max_field: float, depths_mm) -> float:
    """The largest object direction p the tables sample: where the real chief
    ray lands at ``max_field`` x the sensor semi-diagonal (the widest over
    ``depths_mm``) or, if it never gets there, the largest p whose chief ray
    still reaches the sensor."""
    sd = lens.sensor.semi_diagonal_mm
    d = np.asarray(depths_mm, np.float64)
    a = solve_field(lens, d, np.full(d.shape, max_field * sd))
    if a.ok.all() and (a.p > 0).all():
        return float(a.p.max())
    return _largest_reaching_p(lens, math.tan(math.radians(_MAX_ANGLE_DEG)))


def _direction_grid(p_max: float, n: int) -> np.ndarray:
    # n directions uniform in p (uniform in ideal height: the finest where the
    # ideal height grows fastest against the real one) merged with n uniform
    # in angle (which keeps small fields finely sampled when p_max is huge)
    p = np.union1d(np.linspace(0.0, p_max, int(n)), np.tan(np.linspace(0.0, math.atan(p_max), int(n))))
    p = p[np.concatenate([[True], np.diff(p) > 1e-12 * p_max])]
    return np.minimum(p, p_max)


def _table_row(lens, p, real, ok, ideal, depth_mm: float) -> RadialDistortion:
    """One depth's table from its chief rays: cut where a ray fails or the
    height stops increasing beyond field 1; an OpticsError inside field 1."""
    sd = lens.sensor.semi_diagonal_mm
    at = "" if math.isinf(depth_mm) else f" (object at {depth_mm / 1000.0:.4g} m)"
    real, ideal = real.copy(), ideal.copy()
    if not ok.all():
        # near the largest reaching angle aiming is marginal: keep the rays
        # before the first failure if they already reach beyond field 1
        k = int(np.flatnonzero(~ok)[0])
        if k < 2 or real[k - 1] <= sd:
            raise OpticsError(f"lens {lens.id} ({lens.path}): the chief ray at "
                              f"{math.degrees(math.atan(p[k])):.4g} degrees{at} does not reach the sensor, "
                              "though a wider one does: the distortion table has a hole inside field 1")
        p, real, ideal = p[:k], real[:k], ideal[:k]
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
                f"{real[k]:.4g} mm (field {real[k] / sd:.3g}, {math.degrees(math.atan(p[k])):.4g} degrees){at}, "
                "inside the sensor: the distortion folds the image and cannot be warped radially")
        real, ideal = real[:k + 1], ideal[:k + 1]   # keep the monotonic part, beyond field 1
    return RadialDistortion(ideal, real, lens.id)


def _check_table_args(max_field, n) -> None:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputRangeError("n", n, "an integer >= 2")
    if not (isinstance(max_field, (int, float, np.integer, np.floating)) and math.isfinite(max_field)
            and max_field > 0):
        raise InputRangeError("max_field", max_field, "a finite number > 0 (1 = sensor semi-diagonal)")


def _tables(lens, ideal_lens, depths_mm, max_field: float, n: int) -> list[RadialDistortion]:
    """One RadialDistortion a depth: real chief-ray heights of ``lens`` (as
    focused) against the paraxial heights of ``ideal_lens`` (the pinhole's
    scale), the same object directions for every depth."""
    depths = np.asarray(depths_mm, np.float64)
    p = _direction_grid(_p_max(lens, max_field, depths), n)
    real, ok = _chief_heights(lens, np.broadcast_to(p, (depths.size, p.size)), depths[:, None])
    ideal = paraxial_image_height_mm(ideal_lens, np.degrees(np.arctan(p)))
    return [_table_row(lens, p, real[i], ok[i], ideal, float(depths[i])) for i in range(depths.size)]


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
    _check_table_args(max_field, n)
    return _tables(lens, lens, [math.inf], max_field, n)[0]


# the chief-ray map's depths: uniform in diopters from infinity to its near
# limit (linear between them: 0.004 px of 5 um or better for the catalogue, the
# chief ray's depth dependence being pupil aberration, smooth in diopters)
CHIEF_MAP_DEPTHS = 9
# samples of the map's common height grids (uniform): resampling to them adds
# at most 1e-5 mm to the per-depth tables' own interpolation
CHIEF_MAP_HEIGHTS = 2049


@dataclass(frozen=True)
class ChiefRayMap:
    """Where the lens, focused as it is, puts each object direction at each
    depth: the real chief ray's height on the (focused) sensor against the
    ideal (pinhole, paraxial) height of the same direction, for depths
    uniform in diopters from 0 (infinity) to ``diopters[-1]``.

    Refocusing moves the sensor, so the real heights grow with the focus
    (focus breathing: a 50 mm Sonnar's corner moves 4.8 % out from infinity
    to 1.5 m); at one focus they change with the object's depth (pupil
    aberration: 0.54 px of 100 um at the Sonnar's corner between 1.5 and
    6 m; ``python -m lab breathing``). The ideal
    height is the prescription's paraxial one (``paraxial_image_height_mm``
    of the lens before refocusing): the pinhole render's scale.

    ``ideal_from_real(h, diopters)``, ``real_from_ideal(h, diopters)``:
    bilinear in height and diopters on uniform grids; depths nearer than the
    map's near limit use it (as the PSFs do); NaN beyond the reach."""

    diopters: np.ndarray         # (K,) uniform, 0 first
    real_grid_mm: np.ndarray     # (M,) uniform, 0 .. real reach
    ideal_of_real: np.ndarray    # (K, M) ideal height (mm) landing at real_grid_mm at each depth
    ideal_grid_mm: np.ndarray    # (M,) uniform, 0 .. ideal reach
    real_of_ideal: np.ndarray    # (K, M) real height (mm) of ideal_grid_mm at each depth
    lens_id: str = ""
    focus_m: float | None = None

    @property
    def reach_real_mm(self) -> float:
        return float(self.real_grid_mm[-1])

    @property
    def reach_ideal_mm(self) -> float:
        return float(self.ideal_grid_mm[-1])

    @property
    def near_m(self) -> float:
        return 1.0 / float(self.diopters[-1])

    def at(self, diopters: float) -> RadialDistortion:
        """The table of one depth (diopters), as a RadialDistortion."""
        return RadialDistortion(self.ideal_from_real(self.real_grid_mm, diopters), self.real_grid_mm, self.lens_id)

    def _lookup(self, h, diopters, grid, table):
        h = np.asarray(h, np.float64)
        a = np.abs(h)
        kmax = self.diopters.size - 1
        kf = np.clip(np.nan_to_num(np.asarray(diopters, np.float64), nan=0.0) / self.diopters[-1], 0.0, 1.0) * kmax
        k0 = np.minimum(kf.astype(np.int64), kmax - 1)
        t = kf - k0
        m = grid.size - 1
        xf = np.minimum(a / grid[-1], 1.0) * m
        i0 = np.minimum(xf.astype(np.int64), m - 1)
        s = xf - i0
        lo = table[k0, i0] * (1 - s) + table[k0, i0 + 1] * s
        hi = table[k0 + 1, i0] * (1 - s) + table[k0 + 1, i0 + 1] * s
        out = np.sign(h) * (lo * (1 - t) + hi * t)
        return np.where(a <= grid[-1], out, np.nan)

    def ideal_from_real(self, h, diopters=0.0) -> np.ndarray:
        """Ideal height (mm) of the direction whose chief ray from ``diopters``
        (1/m; 0 infinity) lands at real height ``h`` (mm); NaN beyond reach."""
        return self._lookup(h, diopters, self.real_grid_mm, self.ideal_of_real)

    def real_from_ideal(self, h, diopters=0.0) -> np.ndarray:
        """Real height (mm) where the chief ray of the direction imaged ideally
        at ``h`` (mm), from ``diopters``, lands; NaN beyond reach."""
        return self._lookup(h, diopters, self.ideal_grid_mm, self.real_of_ideal)

    def widest_ideal_from_real(self, h) -> np.ndarray:
        """The largest |ideal height| over the map's depths landing at ``h``
        (what a frame's sources need at most)."""
        a = np.abs(np.asarray(h, np.float64))
        out = np.nanmax([np.interp(a, self.real_grid_mm, row) for row in self.ideal_of_real], axis=0)
        return np.where(a <= self.reach_real_mm, np.sign(h) * out, np.nan)


def chief_ray_map(lens, *, focus_m: float | None = None, near_m: float = 0.7, max_field: float = 1.5,
                  n: int = 257, n_depths: int = CHIEF_MAP_DEPTHS) -> ChiefRayMap:
    """The :class:`ChiefRayMap` of ``lens`` focused at ``focus_m`` metres
    (None: the sensor where the prescription puts it), for depths from
    ``near_m`` metres to infinity. Kept in a small process-wide cache (the
    engine's caches: ``dcdi_core.caches``)."""
    from ..optics.lens import lens_fingerprint

    _check_table_args(max_field, n)
    if not (isinstance(near_m, (int, float, np.integer, np.floating)) and math.isfinite(near_m) and near_m > 0):
        raise InputRangeError("near_m", near_m, "a finite distance > 0 metres")
    if focus_m is not None and not (focus_m > 0):
        raise InputRangeError("focus_m", focus_m, "> 0 metres, or inf, or None (as prescribed)")
    if isinstance(n_depths, bool) or not isinstance(n_depths, (int, np.integer)) or n_depths < 2:
        raise InputRangeError("n_depths", n_depths, "an integer >= 2")
    key = (lens_fingerprint(lens), None if focus_m is None else float(focus_m), float(near_m), float(max_field),
           int(n), int(n_depths))
    return _cached_map(key, _Held(lens))


class _Held:
    """A lens carried past the cache's key (which is its fingerprint)."""

    def __init__(self, lens):
        self.lens = lens

    def __hash__(self):
        return 0

    def __eq__(self, other):
        return isinstance(other, _Held)


@caches.lru("chief-ray maps", maxsize=8)
def _cached_map(key, held: _Held) -> ChiefRayMap:
    from ..optics.paraxial import refocused

    _, focus_m, near_m, max_field, n, n_depths = key
    lens = held.lens
    focused = lens if focus_m is None else refocused(lens, focus_m)
    diopters = np.linspace(0.0, 1.0 / near_m, n_depths)
    depths_mm = np.where(diopters > 0, 1000.0 / np.where(diopters > 0, diopters, 1.0), math.inf)
    rows = _tables(focused, lens, depths_mm, max_field, n)
    reach_real = min(r.reach_real_mm for r in rows)
    reach_ideal = min(r.reach_ideal_mm for r in rows)
    real_grid = np.linspace(0.0, reach_real, CHIEF_MAP_HEIGHTS)
    ideal_grid = np.linspace(0.0, reach_ideal, CHIEF_MAP_HEIGHTS)
    ideal_of_real = np.stack([np.interp(real_grid, r.real_mm, r.ideal_mm) for r in rows])
    real_of_ideal = np.stack([np.interp(ideal_grid, r.ideal_mm, r.real_mm) for r in rows])
    return ChiefRayMap(diopters, real_grid, ideal_of_real, ideal_grid, real_of_ideal, lens.id, focus_m)


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
