"""First-order (paraxial) analysis by 2x2 ray-transfer matrices.

Rays are (y, n u): height y in mm and reduced angle n u. Refraction at a
surface of curvature c between indices n and n' is [[1, 0], [-c (n' - n), 1]],
transfer over t mm in index n is [[1, t / n], [0, 1]]. Object and image space
are air. Distances follow the lens frame: z along the axis, first vertex at
z = 0; positive = towards the sensor.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .lens import Lens


def _refraction(c: float, n: float, n2: float) -> np.ndarray:
    return np.array([[1.0, 0.0], [-c * (n2 - n), 1.0]])


def _transfer(t: float, n: float) -> np.ndarray:
    return np.array([[1.0, t / n], [0.0, 1.0]])


def matrix(lens: Lens, wavelength_nm: float, first: int, last: int, *,
           refract_first: bool = True, refract_last: bool = True) -> np.ndarray:
    """Matrix from the vertex plane of surface ``first`` to that of ``last``
    (0-based, first <= last), with or without the refraction at each end."""
    n = lens.refractive_indices(np.array([wavelength_nm]))[:, 0]
    m = np.eye(2)
    for i in range(first, last + 1):
        if i > first:
            m = _transfer(lens.surfaces[i - 1].thickness_mm, n[i]) @ m
        if (i > first or refract_first) and (i < last or refract_last):
            m = _refraction(lens.surfaces[i].curvature, n[i], n[i + 1]) @ m
    return m


@dataclass(frozen=True)
class FirstOrder:
    """First-order properties at one wavelength (lengths in mm)."""

    wavelength_nm: float
    effective_focal_length_mm: float
    back_focal_length_mm: float            # last vertex -> rear focal point
    front_focal_length_mm: float           # front focal point -> first vertex (positive: in front)
    f_number: float                        # EFL / entrance pupil diameter (object at infinity)
    entrance_pupil_position_mm: float      # from the first vertex, + towards the sensor
    entrance_pupil_diameter_mm: float
    exit_pupil_position_mm: float          # from the last vertex, + towards the sensor
    exit_pupil_diameter_mm: float
    sensor_distance_mm: float              # last vertex -> sensor
    in_focus_object_distance_m: float      # from the first vertex; < 0: virtual object; inf: focused at infinity
    lens_matrix: np.ndarray                # first vertex -> last vertex, refractions included

    @property
    def in_focus_is_virtual(self) -> bool:
        return self.in_focus_object_distance_m < 0


def first_order(lens: Lens, wavelength_nm: float | None = None) -> FirstOrder:
    """EFL, BFL, F-number, pupils and the in-focus object distance."""
    wl = lens.wavelength_nm if wavelength_nm is None else float(wavelength_nm)
    last = len(lens.surfaces) - 1
    stop = lens.stop_index
    (a, b), (c, d) = m = matrix(lens, wl, 0, last)
    if c == 0.0:
        from .errors import AfocalLensError
        raise AfocalLensError(f"{lens.path}: the lens is afocal (zero paraxial power): it has no focal length and "
                              "forms no image on a sensor; check the radii (a flat or a window is not a lens)")
    efl = -1.0 / c
    bfl = -a / c
    ffl = -d / c   # front focal point at z = d / c from the first vertex
    # entrance pupil: image of the stop through the surfaces in front of it
    (pa, pb), _ = matrix(lens, wl, 0, stop, refract_last=False)
    ep_z = pb / pa
    ep_d = 2.0 * lens.surfaces[stop].semi_diameter_mm / abs(pa)
    # exit pupil: image of the stop through the surfaces behind it
    n_stop = lens.refractive_indices(np.array([wl]))[stop + 1, 0]
    (qa, qb), (qc, qd) = matrix(lens, wl, stop, last, refract_first=False)
    # ray from the stop centre: (y, n u) = (0, n_stop * 1); exit space is air
    y_l, u_l = qb * n_stop, qd * n_stop
    xp_z = -y_l / u_l if u_l != 0 else math.inf
    xp_d = 2.0 * lens.surfaces[stop].semi_diameter_mm * abs(qa + xp_z * qc) if math.isfinite(xp_z) else math.inf
    s = lens.surfaces[-1].thickness_mm
    denom = a + s * c
    obj = math.inf if denom == 0 else -(b + s * d) / denom
    return FirstOrder(wl, efl, bfl, ffl, efl / ep_d, ep_z, ep_d, xp_z, xp_d, s,
                      obj / 1000.0 if math.isfinite(obj) else math.inf, m)


def image_distance_mm(lens: Lens, depth_m, wavelength_nm: float | None = None) -> np.ndarray:
    """Paraxial image distance from the last vertex (mm) of an axial object at
    ``depth_m`` metres in front of the first vertex (``inf`` allowed)."""
    wl = lens.wavelength_nm if wavelength_nm is None else float(wavelength_nm)
    (a, b), (c, d) = matrix(lens, wl, 0, len(lens.surfaces) - 1)
    depth = np.asarray(depth_m, dtype=np.float64) * 1000.0
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(np.isinf(depth), -a / c, -(a * depth + b) / (c * depth + d))
    return q


def paraxial_image_height_mm(lens: Lens, field_angle_deg, wavelength_nm: float | None = None):
    """Paraxial chief-ray height on the sensor plane for an object at infinity
    at ``field_angle_deg`` (the chief ray through the paraxial entrance pupil)."""
    fo = first_order(lens, wavelength_nm)
    (a, b), (c, d) = fo.lens_matrix
    u0 = np.tan(np.radians(np.asarray(field_angle_deg, dtype=np.float64)))
    y0 = -fo.entrance_pupil_position_mm * u0
    y_last = a * y0 + b * u0
    u_last = c * y0 + d * u0
    return y_last + fo.sensor_distance_mm * u_last


def image_distance_at_diopters_mm(lens: Lens, diopters, wavelength_nm: float | None = None) -> np.ndarray:
    """Paraxial image distance from the last vertex (mm) of an axial object at
    ``diopters`` (1/m, from the first vertex): 0 is infinity, a negative value
    a virtual object (q = -(1000 a + b D) / (1000 c + d D))."""
    wl = lens.wavelength_nm if wavelength_nm is None else float(wavelength_nm)
    (a, b), (c, d) = matrix(lens, wl, 0, len(lens.surfaces) - 1)
    D = np.asarray(diopters, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -(1000.0 * a + b * D) / (1000.0 * c + d * D)


def prescribed_focus_diopters(lens: Lens, wavelength_nm: float | None = None) -> float:
    """The paraxial focus (1/m from the first vertex) that the prescribed sensor
    position q (the last thickness, mm) is equivalent to: D = 1000 * -(a + q c)
    / (q d + b). 0 is infinity; negative: the sensor sits inside the infinity
    focus (a virtual object would be in focus)."""
    wl = lens.wavelength_nm if wavelength_nm is None else float(wavelength_nm)
    (a, b), (c, d) = matrix(lens, wl, 0, len(lens.surfaces) - 1)
    q = lens.surfaces[-1].thickness_mm
    return float(1000.0 * -(a + q * c) / (q * d + b))


def refocused_at_diopters(lens: Lens, diopters: float, wavelength_nm: float | None = None) -> Lens:
    """``refocused`` by the focus in diopters (0: infinity; negative allowed,
    the sensor inside the infinity focus, as some prescriptions put it)."""
    from dataclasses import replace

    from ..errors import InputRangeError

    q = float(image_distance_at_diopters_mm(lens, diopters, wavelength_nm))
    if not (math.isfinite(diopters) and math.isfinite(q) and q > 0):
        raise InputRangeError("focus diopters", diopters,
                              f"a finite focus whose image is real and behind the lens (image distance {q:.4g} mm)")
    surfaces = list(lens.surfaces)
    surfaces[-1] = replace(surfaces[-1], thickness_mm=q)
    return lens.with_surfaces(surfaces)


def refocused(lens: Lens, focus_distance_m: float, wavelength_nm: float | None = None) -> Lens:
    """The lens with its sensor moved (last thickness changed) so that an axial
    object at ``focus_distance_m`` metres (``inf`` allowed) is in paraxial focus."""
    from dataclasses import replace

    from ..errors import InputRangeError

    if not (focus_distance_m > 0):
        raise InputRangeError("focus_distance_m", focus_distance_m, "> 0 metres, or inf")
    q = float(image_distance_mm(lens, focus_distance_m, wavelength_nm))
    if not (math.isfinite(q) and q > 0):
        raise InputRangeError("focus_distance_m", focus_distance_m,
                              f"a distance whose image is real and behind the lens (image distance {q:.4g} mm)")
    surfaces = list(lens.surfaces)
    surfaces[-1] = replace(surfaces[-1], thickness_mm=q)
    return lens.with_surfaces(surfaces)
