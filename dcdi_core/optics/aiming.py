"""Ray aiming: object points, chief rays and pupil samples that fill the real stop.

A source is a (depth, p) pair: depth in mm from the first vertex (``inf`` for
an object at infinity) and p = tan of the field angle seen from the paraxial
entrance pupil. The object point sits at y = -p (depth + z_EP) so that its
image lands at +y; at infinity the rays travel along (0, p, 1)/|.|.

Rays are labelled by where they cross the first vertex plane z = 0, (u, v).
Aiming solves for (u, v) so that the ray meets the real stop surface at a
target point: the stop centre for the chief ray (Newton), and a square grid
over the stop disk for the pupil samples (Newton with the chief ray's
Jacobian, iterated). A mid-lens stop (double Gauss) is therefore filled as it
really is, whatever the pupil aberrations.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import surfaces as S
from .aperture import inside_iris
from ..errors import InputRangeError
from .lens import Lens
from .paraxial import first_order
from .trace import trace

# rays start this far (mm) in front of the most protruding point of the first surface
_START_MARGIN_MM = 1.0


def start_plane_z(lens: Lens) -> float:
    """z (mm) of the plane where rays are launched: in front of every point of
    the first surface's clear aperture."""
    s = lens.surfaces[0]
    r2 = np.linspace(0.0, s.semi_diameter_mm ** 2, 257)
    return float(min(0.0, np.min(s.sag(r2)))) - _START_MARGIN_MM


def launch(lens: Lens, depth_mm, p, u, v, z_ep: float):
    """Origins and directions (..., 3) of rays from sources (depth_mm, p)
    through the points (u, v) of the first vertex plane."""
    depth_mm, p, u, v = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (depth_mm, p, u, v)))
    inf = np.isinf(depth_mm)
    dsafe = np.where(inf, 1.0, depth_mm)
    oy = -p * (dsafe + z_ep)
    dx = np.where(inf, 0.0, u)
    dy = np.where(inf, p, v - oy)
    dz = np.where(inf, 1.0, dsafe)
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    d = np.stack([dx / norm, dy / norm, dz / norm], axis=-1)
    z0 = start_plane_z(lens)
    # start on the launch plane, near the lens: no cancellation for far objects
    s = z0 / d[..., 2]
    o = np.stack([u + s * d[..., 0], v + s * d[..., 1], np.full(u.shape, z0)], axis=-1)
    return o, d


def _stop_is_first_plane(lens) -> bool:
    """The stop is the lens's first surface and a plane (a stop in front)."""
    import math
    stop = lens.surfaces[lens.stop_index]
    return lens.stop_index == 0 and math.isinf(stop.radius_mm) and not getattr(stop, "aspheric_coefficients", None)


def _stop_xy(lens, depth_mm, p, u, v, z_ep, wl):
    o, d = launch(lens, depth_mm, p, u, v, z_ep)
    b = trace(lens, o, d, wl, apertures=False, upto_surface=lens.stop_index)
    return b.position_mm[..., 0], b.position_mm[..., 1], b.valid


@dataclass
class Aimed:
    """Chief rays of a set of sources (arrays shaped like the sources)."""

    depth_mm: np.ndarray
    p: np.ndarray
    v_chief: np.ndarray        # chief ray's v on the first vertex plane (u = 0)
    ok: np.ndarray             # False: no real chief ray (AIM_FAILED)
    z_ep: float


def aim_chief(lens: Lens, depth_mm, p, wavelength_nm=None, *, tol_mm: float = 1e-10,
              max_iter: int = 40) -> Aimed:
    """Chief rays through the centre of the real stop for sources (depth_mm, p)."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    fo = first_order(lens, wl)
    depth_mm, p = np.broadcast_arrays(np.asarray(depth_mm, float), np.asarray(p, float))
    v = -p * fo.entrance_pupil_position_mm
    h = 1e-6 * max(fo.entrance_pupil_diameter_mm, 1e-3)
    ok = np.ones(v.shape, bool)
    done = np.zeros(v.shape, bool)
    zero = np.zeros_like(v)
    for _ in range(max_iter):
        vv = np.stack([v, v + h])
        _, sy, valid = _stop_xy(lens, np.stack([depth_mm] * 2), np.stack([p] * 2),
                                np.stack([zero] * 2), vv, fo.entrance_pupil_position_mm, wl)
        ok &= valid[0] & valid[1]
        slope = (sy[1] - sy[0]) / h
        good = ok & (np.abs(slope) > 1e-12)
        step = np.where(good, sy[0] / np.where(good, slope, 1.0), 0.0)
        # a bounded step keeps a wild first guess from leaving the lens
        lim = 2.0 * max(lens.surfaces[lens.stop_index].semi_diameter_mm, 1.0) / np.maximum(np.abs(slope), 1e-3)
        step = np.clip(step, -lim, lim)
        v = v - np.where(done, 0.0, step)
        done |= np.abs(sy[0]) < tol_mm
        ok &= np.isfinite(v)
        if (done | ~ok).all():
            break
    ok &= done
    return Aimed(depth_mm, p, np.where(ok, v, 0.0), ok, fo.entrance_pupil_position_mm)


def chief_ray_sensor_y(lens, aimed: Aimed, wavelength_nm=None):
    """Height (mm) where each aimed chief ray meets the sensor, and whether it got there
    (apertures ignored: the chief ray of a vignetted field still defines its height)."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    o, d = launch(lens, aimed.depth_mm, aimed.p, 0.0, aimed.v_chief, aimed.z_ep)
    b = trace(lens, o, d, wl, apertures=False)
    return b.position_mm[..., 1], b.valid & aimed.ok


def solve_field(lens: Lens, depth_mm, image_height_mm, wavelength_nm=None, *,
                tol_mm: float = 1e-9, max_iter: int = 40) -> Aimed:
    """Sources whose real chief ray lands at ``image_height_mm`` on the sensor.

    Secant iteration on p; fields the lens cannot image (the chief ray dies or
    the height is out of reach) come back with ``ok = False``."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    depth_mm, target = np.broadcast_arrays(np.asarray(depth_mm, float), np.asarray(image_height_mm, float))
    p_small = np.full(target.shape, 1e-4)
    a0 = aim_chief(lens, depth_mm, p_small, wl)
    h0, ok0 = chief_ray_sensor_y(lens, a0, wl)
    slope = np.where(ok0 & (np.abs(h0) > 0), h0 / p_small, 1.0)
    p_prev, h_prev = p_small, h0
    p = target / slope
    ok = ok0.copy()
    done = np.abs(target) == 0.0
    p = np.where(done, 0.0, p)
    aimed = a0
    for _ in range(max_iter):
        aimed = aim_chief(lens, depth_mm, p, wl)
        h, valid = chief_ray_sensor_y(lens, aimed, wl)
        ok &= valid | done
        err = h - target
        done |= np.abs(err) < tol_mm
        if (done | ~ok).all():
            break
        dh = h - h_prev
        sec = np.where(np.abs(dh) > 1e-15, (p - p_prev) / np.where(np.abs(dh) > 1e-15, dh, 1.0), 1.0 / slope)
        p_new = p - err * sec
        # stay within +-89.9 degrees and do not jump wildly
        p_new = np.clip(p_new, -573.0, 573.0)
        p_prev, h_prev = p, h
        p = np.where(done | ~ok, p, p_new)
    ok &= done
    aimed = aim_chief(lens, depth_mm, p, wl)
    aimed.ok &= ok
    return aimed


def sources(lens: Lens, depth_m, *, field=None, angle_deg=None, wavelength_nm=None) -> Aimed:
    """Chief rays for depths (m, ``inf`` allowed) x fields.

    Exactly one of ``field`` (normalised image height, 1 = sensor
    semi-diagonal) or ``angle_deg`` (field angle in object space, degrees;
    for a finite object the angle seen from the paraxial entrance pupil) is
    given. Returns arrays shaped (n_field, n_depth)."""
    if (field is None) == (angle_deg is None):
        raise TypeError("give exactly one of field= or angle_deg=")
    depth = np.atleast_1d(np.asarray(depth_m, dtype=np.float64))
    bad = ~(depth > 0)
    if bad.any():
        raise InputRangeError("depth_m", float(depth[bad][0]), "> 0 metres, or inf")
    depth_mm = depth * 1000.0
    min_depth = -start_plane_z(lens) + 1e-3
    if (depth_mm < min_depth).any():
        raise InputRangeError("depth_m", float(depth.min()),
                              f">= {min_depth / 1000:.4g} m (in front of the first surface)")
    if field is not None:
        f = np.atleast_1d(np.asarray(field, dtype=np.float64))
        if not np.isfinite(f).all() or (f < 0).any():
            raise InputRangeError("field", f.tolist(), "finite, >= 0 (1 = sensor semi-diagonal)")
        dd, ff = np.meshgrid(depth_mm, f)
        return solve_field(lens, dd, ff * lens.sensor.semi_diagonal_mm, wavelength_nm)
    a = np.atleast_1d(np.asarray(angle_deg, dtype=np.float64))
    if not np.isfinite(a).all() or (np.abs(a) >= 90).any():
        raise InputRangeError("angle_deg", a.tolist(), "(-90, 90) degrees")
    dd, aa = np.meshgrid(depth_mm, a)
    return aim_chief(lens, dd, np.tan(np.radians(aa)), wavelength_nm)


def stop_grid(lens: Lens, n: int) -> np.ndarray:
    """Targets (P, 2) in mm: the centres of an n x n square grid over the stop
    that fall inside the stop's semi-diameter (each sample stands for an
    equal area of the real stop)."""
    if n < 1:
        raise InputRangeError("rays", n, ">= 1")
    stop = lens.surfaces[lens.stop_index]
    r = stop.semi_diameter_mm
    c = ((np.arange(n) + 0.5) / n * 2.0 - 1.0) * r
    x, y = np.meshgrid(c, c)
    keep = x * x + y * y <= r * r
    if stop.blades:                                 # a bladed iris: its polygon (each sample an equal area of it)
        keep &= inside_iris(x, y, stop.blades, stop.blade_rotation_deg, r)
    if n == 1:
        keep[:] = True
    return np.stack([x[keep], y[keep]], axis=-1)


def chief_jacobian(lens: Lens, aimed: Aimed, wavelength_nm=None) -> np.ndarray:
    """d(stop x, y) / d(u, v) at each chief ray (..., 2, 2), by finite differences:
    how the first vertex plane maps onto the real stop around the chief ray."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    dep = aimed.depth_mm[..., None]
    p = aimed.p[..., None]
    v0 = aimed.v_chief[..., None]
    h = 1e-6 * max(lens.surfaces[lens.stop_index].semi_diameter_mm, 1e-3)
    uu = np.concatenate([np.zeros_like(v0), np.full_like(v0, h), np.zeros_like(v0)], axis=-1)
    vv = np.concatenate([v0, v0, v0 + h], axis=-1)
    sx, sy, _ = _stop_xy(lens, dep, p, uu, vv, aimed.z_ep, wl)
    j = np.empty(aimed.p.shape + (2, 2))
    j[..., 0, 0] = (sx[..., 1] - sx[..., 0]) / h
    j[..., 1, 0] = (sy[..., 1] - sy[..., 0]) / h
    j[..., 0, 1] = (sx[..., 2] - sx[..., 0]) / h
    j[..., 1, 1] = (sy[..., 2] - sy[..., 0]) / h
    return j


def pupil_rays(lens: Lens, aimed: Aimed, targets: np.ndarray, wavelength_nm=None, *,
               tol_mm: float = 1e-7, max_iter: int = 8):
    """Rays from each source that meet the stop at ``targets`` (P, 2).

    Returns (origins, directions, status, residual_mm): shapes (..., P, 3),
    (..., P, 3), (..., P) where ... is the sources' shape; status is
    AIM_FAILED where the source has no chief ray, else OK; residual_mm is the
    largest distance between a ray's real stop point and its target after the
    iterations."""
    wl = lens.wavelength_nm if wavelength_nm is None else wavelength_nm
    z_ep = aimed.z_ep
    dep = aimed.depth_mm[..., None]
    p = aimed.p[..., None]
    v0 = aimed.v_chief[..., None]
    h = 1e-6 * max(lens.surfaces[lens.stop_index].semi_diameter_mm, 1e-3)
    j = chief_jacobian(lens, aimed, wl)
    det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
    good = aimed.ok & np.isfinite(det) & (np.abs(det) > 1e-12)
    det = np.where(good, det, 1.0)
    inv = np.empty_like(j)
    inv[..., 0, 0] = j[..., 1, 1] / det
    inv[..., 1, 1] = j[..., 0, 0] / det
    inv[..., 0, 1] = -j[..., 0, 1] / det
    inv[..., 1, 0] = -j[..., 1, 0] / det
    inv = np.where(good[..., None, None], inv, np.eye(2))
    tx, ty = targets[:, 0], targets[:, 1]
    iv = inv[..., None, :, :]
    u = iv[..., 0, 0] * tx + iv[..., 0, 1] * ty
    v = v0 + iv[..., 1, 0] * tx + iv[..., 1, 1] * ty
    # Newton with a per-ray finite-difference Jacobian, only on the rays not
    # yet within tol_mm of their target (the linear start is exact for a stop
    # in front of the lens, so those lenses need no iteration)
    shape = u.shape
    u, v = u.ravel().copy(), v.ravel().copy()
    dep_f = np.broadcast_to(dep, shape).ravel()
    p_f = np.broadcast_to(p, shape).ravel()
    tx_f = np.broadcast_to(tx, shape).ravel()
    ty_f = np.broadcast_to(ty, shape).ravel()
    active = np.flatnonzero(np.broadcast_to(good[..., None], shape).ravel())
    residual = 0.0
    if _stop_is_first_plane(lens):
        # the launch's (u, v) lie on the first vertex plane, which is the stop: the linear start is each
        # target itself, and checking it would trace every ray to the stop a second time for nothing
        active = active[:0]
    for it in range(max_iter + 1):
        if active.size == 0:
            break
        ua, va = u[active], v[active]
        sx, sy, valid = _stop_xy(lens, dep_f[active], p_f[active], ua, va, z_ep, wl)
        rx, ry = sx - tx_f[active], sy - ty_f[active]
        res = np.where(valid, np.hypot(rx, ry), 0.0)
        residual = float(res.max())
        keep = res >= tol_mm
        if it == max_iter or not keep.any():
            break
        active, ua, va, rx, ry = active[keep], ua[keep], va[keep], rx[keep], ry[keep]
        sx, sy = sx[keep], sy[keep]
        d_a, p_a = dep_f[active], p_f[active]
        sxu, syu, _ = _stop_xy(lens, d_a, p_a, ua + h, va, z_ep, wl)
        sxv, syv, _ = _stop_xy(lens, d_a, p_a, ua, va + h, z_ep, wl)
        a11, a21 = (sxu - sx) / h, (syu - sy) / h
        a12, a22 = (sxv - sx) / h, (syv - sy) / h
        det = a11 * a22 - a12 * a21
        ok = np.isfinite(det) & (np.abs(det) > 1e-12)
        det = np.where(ok, det, 1.0)
        du = np.where(ok, (a22 * rx - a12 * ry) / det, 0.0)
        dv = np.where(ok, (a11 * ry - a21 * rx) / det, 0.0)
        u[active] = ua - du
        v[active] = va - dv
    u, v = u.reshape(shape), v.reshape(shape)
    o, d = launch(lens, dep, p, u, v, z_ep)
    status = np.where(good[..., None], S.OK, S.AIM_FAILED).astype(np.uint8)
    status = np.broadcast_to(status, u.shape).copy()
    return o, d, status, residual
