"""Real-ray analysis: spot diagrams, real field angles, distortion, working F-number.

All heights in mm on the sensor plane, depths in metres from the first vertex
(``inf`` for infinity), angles in degrees, wavelengths in nm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .aiming import Aimed, aim_chief, chief_ray_sensor_y, launch, pupil_rays, sources, stop_grid
from .lens import Lens
from .paraxial import paraxial_image_height_mm
from .trace import RayBundle, trace


@dataclass
class Spots:
    """Rays of sources x wavelengths on the sensor.

    ``bundle`` has shape (n_field, n_depth, n_wavelength, P); ``chief_y_mm``
    (n_field, n_depth, n_wavelength) is the chief ray's height per wavelength.
    """

    aimed: Aimed
    wavelengths_nm: np.ndarray
    bundle: RayBundle
    chief_y_mm: np.ndarray
    aim_residual_mm: float

    def _xy(self):
        return self.bundle.position_mm[..., 0], self.bundle.position_mm[..., 1]

    @property
    def n_pupil(self) -> int:
        return self.bundle.shape[-1]

    @property
    def valid_count(self) -> np.ndarray:
        return self.bundle.valid.sum(axis=-1)

    @property
    def vignetted_fraction(self) -> np.ndarray:
        """Fraction of the rays that fill the real stop which do not reach the sensor."""
        return 1.0 - self.valid_count / self.n_pupil

    @property
    def centroid_mm(self) -> np.ndarray:
        """(..., 2) centroid [x, y] of the surviving rays (0 where none survive)."""
        x, y = self._xy()
        w = self.bundle.valid
        n = np.maximum(w.sum(axis=-1), 1)
        return np.stack([(x * w).sum(-1) / n, (y * w).sum(-1) / n], axis=-1)

    @property
    def rms_radius_mm(self) -> np.ndarray:
        """RMS distance of the surviving rays from their centroid (0 where none survive)."""
        x, y = self._xy()
        w = self.bundle.valid
        n = np.maximum(w.sum(axis=-1), 1)
        c = self.centroid_mm
        r2 = (x - c[..., 0:1]) ** 2 + (y - c[..., 1:2]) ** 2
        return np.sqrt((r2 * w).sum(-1) / n)


def trace_sources(lens: Lens, aimed: Aimed, wavelengths_nm, rays: int = 128, *,
                  dtype=np.float64) -> Spots:
    """Trace an ``rays`` x ``rays`` grid over the real stop from every source."""
    wl = np.atleast_1d(np.asarray(wavelengths_nm, dtype=np.float64))
    targets = stop_grid(lens, rays)
    o, d, status, resid = pupil_rays(lens, aimed, targets)
    o, d, status = o[:, :, None], d[:, :, None], status[:, :, None]
    b = trace(lens, o, d, wl[None, None, :, None], dtype=dtype, status=status)
    oc, dc = launch(lens, aimed.depth_mm, aimed.p, 0.0, aimed.v_chief, aimed.z_ep)
    cb = trace(lens, oc[:, :, None], dc[:, :, None], wl[None, None, :], apertures=False)
    chief = np.where(cb.valid & aimed.ok[..., None], cb.position_mm[..., 1], 0.0)
    return Spots(aimed, wl, b, chief, resid)


def spot_diagram(lens: Lens, depth_m, wavelengths_nm, *, field=None, angle_deg=None,
                 rays: int = 128, dtype=np.float64) -> Spots:
    """Spots for fields (normalised) or angles (deg) x depths (m) x wavelengths (nm)."""
    aimed = sources(lens, depth_m, field=field, angle_deg=angle_deg)
    return trace_sources(lens, aimed, wavelengths_nm, rays, dtype=dtype)


def real_field_angle_deg(lens: Lens, field, wavelength_nm=None) -> np.ndarray:
    """Object-space angle (deg) of the real chief ray from infinity that lands
    at normalised image height ``field``; NaN-free: -1 where no such ray."""
    a = sources(lens, [math.inf], field=field, wavelength_nm=wavelength_nm)
    ang = np.degrees(np.arctan(a.p[:, 0]))
    return np.where(a.ok[:, 0], ang, -1.0)


def distortion(lens: Lens, angle_deg, wavelength_nm=None) -> np.ndarray:
    """Relative distortion (real - paraxial) / paraxial chief-ray height on the
    sensor plane, object at infinity. 0 at 0 degrees by definition."""
    angle = np.atleast_1d(np.asarray(angle_deg, dtype=np.float64))
    a = aim_chief(lens, np.full(angle.shape, np.inf), np.tan(np.radians(angle)), wavelength_nm)
    real, ok = chief_ray_sensor_y(lens, a, wavelength_nm)
    par = paraxial_image_height_mm(lens, angle, wavelength_nm)
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.where(ok & (par != 0), real / np.where(par != 0, par, 1.0) - 1.0, 0.0)
    return dist


def working_f_number(lens: Lens, wavelength_nm=None) -> float:
    """Real working F-number 1 / (2 sin u') of the marginal ray of an axial
    object at infinity (image space is air)."""
    a = aim_chief(lens, np.array([np.inf]), np.array([0.0]), wavelength_nm)
    r = lens.surfaces[lens.stop_index].semi_diameter_mm
    o, d, status, _ = pupil_rays(lens, a, np.array([[0.0, r]]))
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    b = trace(lens, o, d, wl, apertures=False, status=status)
    if not b.valid.all():
        return math.inf
    sin_u = math.hypot(b.direction[0, 0, 0], b.direction[0, 0, 1])
    return 1.0 / (2.0 * sin_u)


def best_focus_depth_m(lens: Lens, wavelength_nm=None, *, rays: int = 48) -> float:
    """Object depth (m) that the real on-axis spot is smallest for (golden-section
    search over inverse depth 0 .. 1/0.05 m^-1); inf when infinity is sharpest."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm

    def rms(inv_m):
        depth = np.where(inv_m > 0, 1.0 / np.maximum(inv_m, 1e-12), np.inf)
        s = spot_diagram(lens, depth, [wl], field=[0.0], rays=rays)
        return s.rms_radius_mm[0, :, 0]

    grid = np.linspace(0.0, 20.0, 81)
    values = rms(grid)
    i = int(np.argmin(values))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    g = (math.sqrt(5) - 1) / 2
    for _ in range(30):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        fa, fb = rms(np.array([a, b]))
        if fa < fb:
            hi = b
        else:
            lo = a
    inv = 0.5 * (lo + hi)
    return math.inf if inv < 1e-6 else 1.0 / inv
