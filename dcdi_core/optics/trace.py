"""Sequential real-ray tracer (numpy, vectorised, batched over any leading shape).

Rays are traced in the lens frame: z along the optical axis, the first vertex
at z = 0, lengths in mm. Internally the rays are kept as separate x, y, z,
dx, dy, dz arrays (structure of arrays) and processed in chunks that fit in
the CPU cache, spread over the shared thread pool (``dcdi_core.parallel``;
numpy releases the GIL inside its element-wise loops, so chunks run in
parallel).

Every ray carries a status code (``surfaces.OK`` or the first reason it died)
and the index of the surface where it died. A dead ray is frozen at its last
valid position and direction: it never produces NaN or inf downstream.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..parallel import thread_pool
from . import surfaces as S
from .aperture import inside_iris
from .profiles import Plane, Profile, profile_of

# rays per chunk: 256 kB per coordinate array keeps a chunk's working set in
# cache while amortising numpy's per-call overhead (measured: dcdi bench trace)
CHUNK_BYTES = 1 << 18


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
    profile: Profile     # the surface's kind: its root, sheet and normal
    sd2: float           # squared semi-diameter (inf: no aperture)
    refract: bool        # False where the media on both sides are identical
    index: int
    iris: tuple | None = None   # a bladed stop: (blades, rotation deg, semi-diameter mm)


def _steps(lens, upto: int | None, apertures: bool) -> list[_Step]:
    out = []
    last = len(lens.surfaces) if upto is None else upto + 1
    for i in range(last):
        s = lens.surfaces[i]
        before = lens.surfaces[i - 1].material if i > 0 else None
        same = (before is s.material) or (before is None and s.material.name == "air")
        iris = (s.blades, s.blade_rotation_deg, s.semi_diameter_mm) if apertures and s.blades else None
        out.append(_Step(float(lens.vertex_z_mm[i]), profile_of(s),
                         s.semi_diameter_mm ** 2 if apertures else np.inf, not same, i, iris))
    if upto is None:  # the sensor: a plane without aperture
        out.append(_Step(float(lens.sensor_z_mm), Plane(), np.inf, False, len(lens.surfaces)))
    return out


def _kill(status, failed, mask, code, index):
    """Give ``code`` to the rays in ``mask`` that are still alive."""
    new = mask & (status == S.OK)
    status[new] = code
    failed[new] = index


def _trace_chunk(steps, mu_tables, widx, x, y, z, dx, dy, dz, status, failed,
                 newton_tol, newton_iter):
    """Trace one chunk in place through ``steps``: each surface's kind
    (``optics.profiles``) gives the root from the vertex plane, the sheet
    check and the normal; the kernel moves, clips and refracts.

    Written for speed: each failure test is first a single min/max reduction,
    and masks are built only when some ray really fails; dead rays are frozen
    with masked copies."""
    dt = x.dtype
    alive = [bool((status == S.OK).all())]

    for st in steps:
        def kill(mask, code, index=st.index):
            _kill(status, failed, mask, code, index)
            alive[0] = False

        if dz.min() <= S.MIN_FORWARD_COSINE:
            backward = dz <= S.MIN_FORWARD_COSINE
            kill(backward, S.BACKWARD)
            dzs = np.where(backward, 1.0, dz)
        else:
            dzs = dz
        # move to the vertex plane first: no cancellation in the quadratic below
        t = (st.z_vertex - z) / dzs
        xs = x + t * dx
        ys = y + t * dy
        prof = st.profile
        zl = None
        t1 = prof.root(xs, ys, dx, dy, dz, kill, newton_tol, newton_iter)
        if t1 is not None:
            xs += t1 * dx
            ys += t1 * dy
            zl = t1 * dz
            t += t1
            prof.check_sheet(zl, kill)
        r2 = xs * xs + ys * ys
        # the surface behind the ray (beyond rounding: 1e-9 mm), or outside the aperture
        if t.min() < -1e-9:
            kill(t < -1e-9, S.BACKWARD)
        if np.isfinite(st.sd2) and r2.max() > st.sd2:
            kill(r2 > st.sd2, S.VIGNETTED)
        if st.iris is not None:
            outside = ~inside_iris(xs, ys, *st.iris)
            if outside.any():
                kill(outside, S.VIGNETTED)
        ok = None if alive[0] else status == S.OK
        if zl is not None:
            zl += st.z_vertex
        _assign(ok, (x, y, z), (xs, ys, zl if zl is not None else st.z_vertex))
        if not st.refract:
            continue
        # unit normal, oriented along +z at the vertex (local z: as the global one minus the vertex)
        nx, ny, nz = prof.normal(xs, ys, None if zl is None else zl - st.z_vertex, r2, dt)
        mu = mu_tables[st.index]
        if widx is not None:
            mu = mu[widx]
        cos_i = dx * nx + dy * ny + dz * nz
        if np.min(cos_i) < 0.0:  # orient the normal along the ray
            sgn = np.where(cos_i < 0.0, -1.0, 1.0).astype(dt)
            nx, ny, nz = nx * sgn, ny * sgn, nz * sgn
            cos_i = cos_i * sgn
        kk = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
        if np.min(kk) < 0.0:
            tir = kk < 0.0
            kill(tir, S.TIR)
            kk[tir] = 0.0
            ok = status == S.OK
        g = np.sqrt(kk) - mu * cos_i
        _assign(ok, (dx, dy, dz), (mu * dx + g * nx, mu * dy + g * ny, mu * dz + g * nz))


def _assign(ok, targets, values):
    """targets[...] = values, only where ``ok`` (all where ok is None)."""
    for tgt, val in zip(targets, values):
        if ok is None:
            tgt[...] = val
        else:
            np.copyto(tgt, val, where=ok)


def trace(lens, origins, directions, wavelength_nm, *, dtype=np.float64,
          apertures: bool = True, upto_surface: int | None = None,
          newton_tol: float | None = None, newton_iter: int = 30,
          status=None, chunk: int | None = None) -> RayBundle:
    """Trace rays through ``lens`` to its sensor plane.

    origins (..., 3) mm, directions (..., 3) unit vectors, in the lens frame;
    wavelength_nm broadcastable to the leading shape (kept small: indices are
    computed once per distinct wavelength). ``dtype`` float64 (default) or
    float32. ``apertures=False`` ignores semi-diameters (ray aiming uses it).
    ``upto_surface`` stops at that surface (0-based) instead of the sensor,
    without refracting there. ``status`` gives rays already dead before the
    trace (e.g. aiming failures). ``chunk``: rays per chunk (default:
    CHUNK_BYTES of each coordinate); a chunk as large as the bundle traces it
    in one piece on the calling thread (the benchmark's baseline). Returns a
    :class:`RayBundle`.
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
        steps[-1] = replace(steps[-1], refract=False)
    tol = newton_tol if newton_tol is not None else (1e-12 if dtype == np.float64 else 1e-5)

    def run(sl):
        _trace_chunk(steps, mu_tables, None if widx is None else widx[sl],
                     x[sl], y[sl], z[sl], dx[sl], dy[sl], dz[sl], st[sl], failed[sl],
                     tol, newton_iter)

    if chunk is None:
        chunk = max(1024, CHUNK_BYTES // dtype.itemsize)
    elif isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"chunk = {chunk!r}: allowed an integer >= 1 (rays)")
    slices = [slice(i, min(i + chunk, n)) for i in range(0, n, chunk)]
    if len(slices) > 1:
        list(thread_pool().map(run, slices))
    elif slices:
        run(slices[0])
    pos = np.stack([x, y, z], axis=-1).reshape(shape + (3,))
    dirs = np.stack([dx, dy, dz], axis=-1).reshape(shape + (3,))
    return RayBundle(pos, dirs, st.reshape(shape), failed.reshape(shape))
