"""Sequential real-ray tracer (numpy, vectorised, batched over any leading shape).

Rays are traced in the lens frame: z along the optical axis, the first vertex
at z = 0, lengths in mm. Internally the rays are kept as separate x, y, z,
dx, dy, dz arrays (structure of arrays) and processed in chunks that fit in
the CPU cache, spread over a thread pool (numpy releases the GIL inside its
element-wise loops, so chunks run in parallel).

Every ray carries a status code (``surfaces.OK`` or the first reason it died)
and the index of the surface where it died. A dead ray is frozen at its last
valid position and direction: it never produces NaN or inf downstream.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from . import surfaces as S

CHUNK = 16384
_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1))
    return _POOL


@dataclass
class RayBundle:
    """Rays after a trace. Arrays share the leading shape ``shape``.

    position_mm, direction: (..., 3); status: (...) uint8 (``surfaces.OK`` =
    alive); failed_surface: (...) int16, the 0-based surface index where the
    ray died (-1 alive; ``n_surfaces`` means the sensor plane).
    """

    position_mm: np.ndarray
    direction: np.ndarray
    status: np.ndarray
    failed_surface: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.status == S.OK

    @property
    def shape(self) -> tuple[int, ...]:
        return self.status.shape

    def counts(self) -> dict[str, int]:
        """How many rays ended with each status, by name."""
        codes, n = np.unique(self.status, return_counts=True)
        return {S.STATUS_NAMES[int(c)]: int(k) for c, k in zip(codes, n)}


@dataclass(frozen=True)
class _Step:
    """What the kernel needs of one surface (or of the sensor plane)."""

    z_vertex: float
    c: float
    k: float
    coeffs: tuple[float, ...]
    sd2: float           # squared semi-diameter (inf: no aperture)
    refract: bool        # False where the media on both sides are identical
    index: int


def _steps(lens, upto: int | None, apertures: bool) -> list[_Step]:
    out = []
    last = len(lens.surfaces) if upto is None else upto + 1
    for i in range(last):
        s = lens.surfaces[i]
        before = lens.surfaces[i - 1].material if i > 0 else None
        same = (before is s.material) or (before is None and s.material.name == "air")
        out.append(_Step(float(lens.vertex_z_mm[i]), s.curvature, float(s.conic),
                         tuple(float(a) for a in s.aspheric_coefficients),
                         s.semi_diameter_mm ** 2 if apertures else np.inf,
                         not same, i))
    if upto is None:  # the sensor: a plane without aperture
        out.append(_Step(float(lens.sensor_z_mm), 0.0, 0.0, (), np.inf, False, len(lens.surfaces)))
    return out


def _kill(status, failed, mask, code, index):
    """Give ``code`` to the rays in ``mask`` that are still alive."""
    new = mask & (status == S.OK)
    status[new] = code
    failed[new] = index


def _trace_chunk(steps, mu_tables, widx, x, y, z, dx, dy, dz, status, failed,
                 newton_tol, newton_iter):
    """Trace one chunk in place through ``steps``.

    Written for speed: failure tests are merged so that a surface where no ray
    dies costs one extra pass, and dead rays are frozen with masked copies."""
    dt = x.dtype
    for st in steps:
        backward = dz <= S.MIN_FORWARD_COSINE
        any_backward = backward.any()
        if any_backward:
            _kill(status, failed, backward, S.BACKWARD, st.index)
            dzs = np.where(backward, 1.0, dz)
        else:
            dzs = dz
        # move to the vertex plane first: no cancellation in the quadratic below
        t = (st.z_vertex - z) / dzs
        xs = x + t * dx
        ys = y + t * dy
        c, k = st.c, st.k
        zl = None
        if c != 0.0 or st.coeffs:
            A = c * (1.0 + k * dz * dz) if k != 0.0 else dt.type(c)
            B = c * (xs * dx + ys * dy) - dz
            C = c * (xs * xs + ys * ys)
            disc = B * B - A * C
            den = B + np.copysign(np.sqrt(np.abs(disc)), B)
            miss = (disc < 0.0) | (den == 0.0)
            any_miss = miss.any()
            if any_miss:
                den[miss] = 1.0
            t1 = -C / den
            if any_miss:
                t1[miss] = 0.0
                _kill(status, failed, miss, S.MISSED, st.index)
            if st.coeffs:
                t1, conv, dom = _newton_asphere(c, k, st.coeffs, xs, ys, dx, dy, dz, t1,
                                                newton_tol, newton_iter)
                _kill(status, failed, ~dom, S.MISSED, st.index)
                _kill(status, failed, ~conv, S.NOT_CONVERGED, st.index)
            xs += t1 * dx
            ys += t1 * dy
            zl = t1 * dz
            t += t1
            # the root must lie on the sheet that holds the vertex
            wrong_sheet = (c * (1.0 + k)) * zl >= 1.0
            if wrong_sheet.any():
                _kill(status, failed, wrong_sheet, S.MISSED, st.index)
        r2 = xs * xs + ys * ys
        # the surface behind the ray (beyond rounding: 1e-9 mm), or outside the aperture
        behind = t < -1e-9
        outside = r2 > st.sd2 if np.isfinite(st.sd2) else None
        bad = behind if outside is None else (behind | outside)
        if bad.any():
            _kill(status, failed, behind, S.BACKWARD, st.index)
            if outside is not None:
                _kill(status, failed, outside, S.VIGNETTED, st.index)
        ok = status == S.OK
        all_ok = ok.all()
        znew = st.z_vertex + zl if zl is not None else np.full_like(x, st.z_vertex)
        if all_ok:
            x[...] = xs
            y[...] = ys
            z[...] = znew
        else:  # dead rays stay where they were (frozen, finite)
            np.copyto(x, xs, where=ok)
            np.copyto(y, ys, where=ok)
            np.copyto(z, znew, where=ok)
        if not st.refract:
            continue
        # unit normal, oriented along +z at the vertex
        if st.coeffs:
            _, slope, _ = S.sag_and_slope(c, k, st.coeffs, r2)
            nx, ny = -2.0 * slope * xs, -2.0 * slope * ys
            nz = 1.0 / np.sqrt(nx * nx + ny * ny + 1.0)
            nx *= nz
            ny *= nz
        else:
            nx, ny = -c * xs, -c * ys
            nz = 1.0 - (c * (1.0 + k)) * zl if zl is not None else np.ones_like(xs)
            if k != 0.0:  # a sphere's implicit normal is already unit length
                inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
                nx *= inv
                ny *= inv
                nz *= inv
        mu = mu_tables[st.index]
        if widx is not None:
            mu = mu[widx]
        cos_i = dx * nx + dy * ny + dz * nz
        flip = cos_i < 0.0
        if flip.any():  # orient the normal along the ray
            sgn = np.where(flip, -1.0, 1.0).astype(dt)
            nx *= sgn
            ny *= sgn
            nz *= sgn
            cos_i *= sgn
        kk = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
        tir = kk < 0.0
        if tir.any():
            _kill(status, failed, tir, S.TIR, st.index)
            kk[tir] = 0.0
            ok = status == S.OK
            all_ok = False
        g = np.sqrt(kk) - mu * cos_i
        ndx = mu * dx + g * nx
        ndy = mu * dy + g * ny
        ndz = mu * dz + g * nz
        if all_ok:
            dx[...] = ndx
            dy[...] = ndy
            dz[...] = ndz
        else:
            np.copyto(dx, ndx, where=ok)
            np.copyto(dy, ndy, where=ok)
            np.copyto(dz, ndz, where=ok)


def _newton_asphere(c, k, coeffs, x0, y0, dx, dy, dz, t, tol, max_iter):
    """Refine the distance t from the vertex plane to an even asphere.

    Solves g(t) = t dz - sag(r2(t)) = 0 with at most ``max_iter`` Newton steps.
    Returns (t, converged, in_domain)."""
    converged = np.zeros(t.shape, dtype=bool)
    for _ in range(max_iter):
        xs = x0 + t * dx
        ys = y0 + t * dy
        r2 = xs * xs + ys * ys
        z, slope, dom = S.sag_and_slope(c, k, coeffs, r2)
        g = t * dz - z
        dg = dz - 2.0 * slope * (xs * dx + ys * dy)
        dg = np.where(np.abs(dg) < 1e-12, 1e-12, dg)
        step = g / dg
        t = t - np.where(converged, 0.0, step)
        converged |= np.abs(step) < tol
        if converged.all():
            break
    xs = x0 + t * dx
    ys = y0 + t * dy
    _, _, dom = S.sag_and_slope(c, k, coeffs, xs * xs + ys * ys)
    t = np.where(np.isfinite(t), t, 0.0)
    return t, converged, dom


def trace(lens, origins, directions, wavelength_nm, *, dtype=np.float64,
          apertures: bool = True, upto_surface: int | None = None,
          newton_tol: float | None = None, newton_iter: int = 30,
          status=None) -> RayBundle:
    """Trace rays through ``lens`` to its sensor plane.

    origins (..., 3) mm, directions (..., 3) unit vectors, in the lens frame;
    wavelength_nm broadcastable to the leading shape (kept small: indices are
    computed once per distinct wavelength). ``dtype`` float64 (default) or
    float32. ``apertures=False`` ignores semi-diameters (ray aiming uses it).
    ``upto_surface`` stops at that surface (0-based) instead of the sensor,
    without refracting there. ``status`` gives rays already dead before the
    trace (e.g. aiming failures). Returns a :class:`RayBundle`.
    """
    dtype = np.dtype(dtype)
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    shape = np.broadcast_shapes(origins.shape[:-1], directions.shape[:-1], wl.shape,
                                np.shape(status) if status is not None else ())
    n = int(np.prod(shape)) if shape else 1
    o = np.broadcast_to(origins, shape + (3,)).reshape(n, 3)
    d = np.broadcast_to(directions, shape + (3,)).reshape(n, 3)
    x, y, z = (np.array(o[:, i], dtype=dtype) for i in range(3))
    dx, dy, dz = (np.array(d[:, i], dtype=dtype) for i in range(3))
    st = np.zeros(n, np.uint8) if status is None else \
        np.broadcast_to(np.asarray(status, np.uint8), shape).reshape(n).copy()
    failed = np.where(st == S.OK, -1, -2).astype(np.int16)

    uniq, inverse = np.unique(wl, return_inverse=True)
    inverse = inverse.reshape(wl.shape)
    widx = None
    if uniq.size > 1:
        widx = np.broadcast_to(inverse, shape).reshape(n).astype(np.int16)
    # mu_tables[i]: n_before / n_after at surface i, one entry per distinct wavelength
    indices = lens.refractive_indices(uniq)              # (n_surfaces + 1, n_wl)
    mu_tables = [(indices[i] / indices[i + 1]).astype(dtype) for i in range(len(lens.surfaces))]
    if widx is None:
        mu_tables = [m[0] for m in mu_tables]
    steps = _steps(lens, upto_surface, apertures)
    if upto_surface is not None:
        steps[-1] = _Step(steps[-1].z_vertex, steps[-1].c, steps[-1].k, steps[-1].coeffs,
                          steps[-1].sd2, False, steps[-1].index)
    tol = newton_tol if newton_tol is not None else (1e-12 if dtype == np.float64 else 1e-5)

    def run(sl):
        _trace_chunk(steps, mu_tables, None if widx is None else widx[sl],
                     x[sl], y[sl], z[sl], dx[sl], dy[sl], dz[sl], st[sl], failed[sl],
                     tol, newton_iter)

    slices = [slice(i, min(i + CHUNK, n)) for i in range(0, n, CHUNK)]
    if len(slices) > 1:
        list(_pool().map(run, slices))
    elif slices:
        run(slices[0])
    pos = np.stack([x, y, z], axis=-1).reshape(shape + (3,))
    dirs = np.stack([dx, dy, dz], axis=-1).reshape(shape + (3,))
    return RayBundle(pos, dirs, st.reshape(shape), failed.reshape(shape))
