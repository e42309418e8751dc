"""Dead-leaves RGB-D scenes in numpy: occluding textured shapes at metric depths.

A Blender-free scene for the dataset factory (``--recipe leaves``). Opaque
shapes (discs, ellipses, rectangles, convex polygons, thin bars and lines),
each at its own depth, are stacked so that nearer shapes hide farther ones,
over a background at the far end of the depth range. What a correction
network learns from is in every frame: depth edges at every scale (shape
sizes follow a power law), texture at every scale (procedural tiles of
fractal noise, stripes, checks, bricks, dots, rings and cells, or the user's
photographs), shading gradients across each shape, and colour.

How a frame is made:

* **Layers.** Depths are log-uniform in ``depth_range_m``; each shape's image
  radius is ``r0 * (z_ref / z) ** perspective_exponent`` with ``r0`` drawn
  from ``p(r0) ~ r0 ** -size_exponent`` (3: scale-invariant dead leaves) and
  ``z_ref`` the range's geometric mean. With exponent 1 the physical size
  (radius times depth over the focal length) is independent of depth, as in
  a world of objects seen in perspective; at 0 the image size is; in
  between, near shapes are larger without near depths filling the frame
  (with 1 and log-uniform depths most pixels would lie nearer than 1 m).
  Shapes are drawn until their summed area is ``coverage`` times the frame's.
* **Rasterising.** The layer index (0 = nearest, the background last) is
  found at the points of a half-pixel grid, ``(2H + 1) x (2W + 1)`` points at
  ``x, y = k / 2`` px (pixel ``(i, j)`` covers ``[j, j + 1) x [i, i + 1)``), as
  a z-buffer: the smallest index covering a point wins. Small shapes are
  tested in vectorised batches, large ones each on its bounding box.
* **Depth** is read at the pixel centres, which are grid points: every
  pixel holds exactly the depth of the one layer covering its centre (the
  nearest there), never an average. :meth:`Layer.covers` is the test used.
* **Colour** is evaluated at every grid point from its layer's texture, then
  integrated over each pixel's square by the trapezoidal rule on the 3 x 3
  points it spans: the box integral of a sensor pixel, anti-aliased edges.

Everything is drawn from ``numpy.random.Generator`` streams seeded from
``seed`` (the layout, the procedural textures and the choice of user
textures each from its own stream): the same arguments give the same bytes.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .. import caches
from ..errors import InputRangeError

SHAPE_KINDS = ("disc", "ellipse", "rectangle", "polygon", "bar", "line")
BACKGROUND = "background"
TILE_KINDS = ("noise", "stripes", "checker", "bricks", "dots", "rings", "cells")
MAX_SIDE_PX = 8192
MAX_POLYGON_EDGES = 8

# the share of each solid kind among the shapes that are not thin (bars, lines)
_SOLID_SHARES = {"disc": 0.2, "ellipse": 0.25, "rectangle": 0.3, "polygon": 0.25}
_FAMILY = {"disc": "ellipse", "ellipse": "ellipse", "rectangle": "box", "bar": "box", "line": "box",
           "polygon": "polygon", BACKGROUND: "all"}
# batched rasterising: shapes whose bounding box spans at most this many grid points a side
_BATCH_SIDES = (8, 12, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96)
_PHOTO_MAX_SIDE_PX = 1024            # user images are box-reduced to at most this, once per process
_PHOTO_CACHE_SIZE = 16
_PHOTOS_PER_FRAME = 4


@dataclass(frozen=True)
class LeavesOptions:
    """What a dead-leaves frame holds. Every field is checked when made."""
    depth_range_m: tuple[float, float] = (0.7, 10.0)   # m, planar: shapes log-uniform in it, background at the far end
    coverage: float = 3.0               # 1: the shapes' summed image area over the frame's (layers per pixel)
    size_exponent: float = 3.0          # 1: p(r) ~ r ** -size_exponent of the image radius; 3 = scale-invariant
    min_radius_px: float = 2.5          # px: the smallest shape's radius at the reference depth
    max_radius_frac: float = 0.6        # 1: the largest radius over the frame's shorter side
    # image radius ~ depth ** -perspective_exponent (1: physical sizes). 0 (classic dead leaves, sizes
    # independent of depth) puts 28/42/18/8/5 % of the pixels at 0.7-1/1-2/2-5/5-10/10 m; 0.25 gave
    # 43/39/11/4/4 %: occlusion already favours near layers, so 0 spreads the depths best
    perspective_exponent: float = 0.0
    thin_share: float = 0.15            # 1: share of the shapes that are bars or lines
    line_width_px: tuple[float, float] = (1.0, 2.5)    # px: a line's width, uniform in it
    texel_per_px: tuple[float, float] = (0.5, 2.0)     # texels per px: texture scale, log-uniform in it
    tile_px: int = 256                  # px: side of a procedural texture tile (power of two)
    tiles: int = 8                      # count: procedural tiles made per frame
    photo_share: float = 0.5            # 1: share of the shapes textured from the user's images, when given
    albedo_range: tuple[float, float] = (0.03, 0.8)    # linear: a shape's brightest colour, log-uniform in it

    def __post_init__(self):
        _check_pair("depth_range_m", self.depth_range_m, 1e-3, 1e4, "0.001 <= near < far <= 10000 metres")
        _check_number("coverage", self.coverage, 0.1, 50.0)
        _check_number("size_exponent", self.size_exponent, 1.5, 5.0)
        _check_number("min_radius_px", self.min_radius_px, 0.5, 256.0)
        _check_number("max_radius_frac", self.max_radius_frac, 0.01, 4.0)
        _check_number("perspective_exponent", self.perspective_exponent, 0.0, 1.0)
        _check_number("thin_share", self.thin_share, 0.0, 1.0)
        _check_pair("line_width_px", self.line_width_px, 0.5, 64.0, "0.5 <= narrow <= wide <= 64 px", strict=False)
        _check_pair("texel_per_px", self.texel_per_px, 0.05, 2.0, "0.05 <= low <= high <= 2 texels per px "
                    "(above 2 the half-pixel grid would skip texels)", strict=False)
        if not isinstance(self.tile_px, int) or isinstance(self.tile_px, bool) or self.tile_px not in (
                32, 64, 128, 256, 512, 1024):
            raise InputRangeError("LeavesOptions.tile_px", self.tile_px, "32, 64, 128, 256, 512 or 1024 px")
        if not isinstance(self.tiles, int) or isinstance(self.tiles, bool) or not 1 <= self.tiles <= 64:
            raise InputRangeError("LeavesOptions.tiles", self.tiles, "an integer 1 to 64")
        _check_number("photo_share", self.photo_share, 0.0, 1.0)
        _check_pair("albedo_range", self.albedo_range, 1e-3, 1.0, "0.001 <= low <= high <= 1 (linear)",
                    strict=False)


def _check_number(field, value, lo, hi):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not lo <= value <= hi:
        raise InputRangeError(f"LeavesOptions.{field}", value, f"a number {lo:g} to {hi:g}")


def _check_pair(field, value, lo, hi, allowed, strict=True):
    try:
        a, b = (float(v) for v in value)
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    except (TypeError, ValueError):
        ok = False
    if not ok or not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi) or (strict and a == b):
        raise InputRangeError(f"LeavesOptions.{field}", value, allowed)


# ----------------------------------------------------------------------------------------------------------------
# layers


@dataclass(frozen=True)
class Layer:
    """One opaque layer of a frame, in pixel coordinates (x right, y down,
    from the frame's top-left corner; pixel centres at half-integers).

    About the centre (``dx = x - cx``, ``dy = y - cy``) a shape has its own
    coordinates ``P = pu * dx + pv * dy``, ``Q = qu * dx + qv * dy`` (its
    rotation over its half-axes); it covers the unit disc ``P^2 + Q^2 <= 1``
    (``ellipse`` family: discs, ellipses) or the square ``|P|, |Q| <= 1``
    (``box``: rectangles, bars, lines); a convex polygon (inscribed in the
    unit circle of P, Q) is the half-planes ``ex * dx + ey * dy <= d`` of its
    ``edges``. The test is made in float32."""
    index: int                           # 0 = nearest; the background is the last
    kind: str                            # one of SHAPE_KINDS, or "background"
    depth_m: float                       # m, planar; exactly representable in float32
    centre_px: tuple[float, float] = (0.0, 0.0)          # (cx, cy) px
    p_row: tuple[float, float] = (1.0, 0.0)              # (pu, pv) 1/px
    q_row: tuple[float, float] = (0.0, 1.0)              # (qu, qv) 1/px
    edges: tuple[tuple[float, float, float], ...] = ()    # polygons: (ex 1/px, ey 1/px, d)

    def covers(self, x, y) -> np.ndarray:
        """Whether the layer covers the points (x, y) px (broadcast arrays):
        the test the depth map is made with."""
        if self.kind == BACKGROUND:
            return np.ones(np.broadcast_shapes(np.shape(x), np.shape(y)), dtype=bool)
        f = np.float32
        e = np.asarray(self.edges, dtype=f).reshape(-1, 3)
        return _inside(_FAMILY[self.kind], f(self.centre_px[0]), f(self.centre_px[1]), f(self.p_row[0]),
                       f(self.p_row[1]), f(self.q_row[0]), f(self.q_row[1]), e[:, 0], e[:, 1], e[:, 2],
                       np.asarray(x, f), np.asarray(y, f))


def _inside(family, cx, cy, pu, pv, qu, qv, ex, ey, ed, x, y):
    """The inside test of one shape (float32 scalars) or a batch (float32
    arrays shaped to broadcast against x, y; polygon edges on a last axis).
    The arithmetic is elementwise, so a point gets the same answer either
    way (what makes the depth map exact)."""
    dx = x - cx
    dy = y - cy
    if family == "polygon":
        inside = ex[..., 0] * dx + ey[..., 0] * dy <= ed[..., 0]
        for k in range(1, ex.shape[-1]):
            inside &= ex[..., k] * dx + ey[..., k] * dy <= ed[..., k]
        return inside
    p = pu * dx + pv * dy
    q = qu * dx + qv * dy
    if family == "ellipse":
        p *= p
        q *= q
        p += q
        return p <= 1.0
    np.abs(p, out=p)
    np.abs(q, out=q)
    np.maximum(p, q, out=p)
    return p <= 1.0


@dataclass
class _Shapes:
    """The frame's shapes as arrays, nearest first (the background is not
    among them); the inside test's parameters (:class:`Layer`) are float32."""
    kind: np.ndarray        # int, index into SHAPE_KINDS
    depth: np.ndarray       # m, float32-exact float64
    cx: np.ndarray          # px
    cy: np.ndarray
    pu: np.ndarray          # 1/px
    pv: np.ndarray
    qu: np.ndarray
    qv: np.ndarray
    edges: np.ndarray       # (n, MAX_POLYGON_EDGES, 3): (ex, ey, d); unused edges (0, 0, 1) hold everywhere
    n_edges: np.ndarray     # int
    ext_x: np.ndarray       # px, float64: the shape's half-extent along x and y (bounding boxes)
    ext_y: np.ndarray

    def __len__(self):
        return len(self.kind)


def _f32_within(z, lo, hi):
    """z (metres) rounded to float32, kept inside [lo, hi] after rounding."""
    z32 = z.astype(np.float32)
    z32 = np.where(z32.astype(np.float64) < lo, np.nextafter(z32, np.float32(np.inf)), z32)
    z32 = np.where(z32.astype(np.float64) > hi, np.nextafter(z32, np.float32(0)), z32)
    return z32.astype(np.float64)


def _far_depth(options) -> float:
    return float(_f32_within(np.array([options.depth_range_m[1]]), *options.depth_range_m)[0])


def _draw_batch(rng, n, height, width, options):
    """n shapes' parameters (unsorted) and their areas (px^2)."""
    near, far = options.depth_range_m
    z = near * (far / near) ** rng.random(n)
    r_lo = options.min_radius_px
    r_hi = max(options.max_radius_frac * min(height, width), r_lo * 1.01)
    alpha = options.size_exponent
    # inverse CDF of p(r) ~ r^-alpha on [r_lo, r_hi]
    u = rng.random(n)
    e = 1.0 - alpha
    r = (r_lo ** e + u * (r_hi ** e - r_lo ** e)) ** (1.0 / e)
    r = r * (math.sqrt(near * far) / z) ** options.perspective_exponent
    r = np.minimum(r, r_hi)

    solid = list(_SOLID_SHARES)
    shares = np.array([_SOLID_SHARES[k] for k in solid]) * (1.0 - options.thin_share)
    probs = np.concatenate([shares, [options.thin_share / 2, options.thin_share / 2]])
    order = solid + ["bar", "line"]
    kind = np.array([SHAPE_KINDS.index(k) for k in order])[rng.choice(len(order), size=n, p=probs / probs.sum())]

    aspect = np.exp(rng.uniform(0.0, math.log(3.0), n))
    aspect = np.where(kind == SHAPE_KINDS.index("disc"), 1.0, aspect)
    aspect = np.where(kind == SHAPE_KINDS.index("bar"), np.exp(rng.uniform(math.log(4), math.log(16), n)), aspect)
    a = r * np.sqrt(aspect)
    b = r / np.sqrt(aspect)
    is_line = kind == SHAPE_KINDS.index("line")
    line_half = rng.uniform(*options.line_width_px, n) / 2
    a = np.where(is_line, r * rng.uniform(3.0, 12.0, n), a)
    b = np.where(is_line, line_half, b)
    a = np.maximum(a, 0.5)
    b = np.maximum(b, 0.5)

    angle = rng.uniform(0.0, math.pi, n)
    margin_x, margin_y = 0.1 * width, 0.1 * height
    cx = rng.uniform(-margin_x, width + margin_x, n)
    cy = rng.uniform(-margin_y, height + margin_y, n)

    edges, n_edges, poly_area = _polygons(rng, n)
    area = np.select([kind <= SHAPE_KINDS.index("ellipse"), kind == SHAPE_KINDS.index("polygon")],
                     [math.pi * a * b, poly_area * a * b], 4.0 * a * b)
    return dict(kind=kind, depth=z, cx=cx, cy=cy, cos=np.cos(angle), sin=np.sin(angle), a=a, b=b,
                edges=edges, n_edges=n_edges), area


def _polygons(rng, n):
    """Convex polygons of 3 to MAX_POLYGON_EDGES vertices inscribed in the
    unit circle, as edge half-planes, and their areas (unit circle: pi)."""
    m = MAX_POLYGON_EDGES
    k = rng.integers(3, m + 1, n)
    used = np.arange(m)[None, :] < k[:, None]
    gaps = np.where(used, rng.uniform(0.5, 1.5, (n, m)), 0.0)
    gaps = gaps / gaps.sum(axis=1, keepdims=True) * (2 * math.pi)
    start = rng.uniform(0.0, 2 * math.pi, n)[:, None]
    mid = start + np.cumsum(gaps, axis=1) - gaps / 2      # the edge's normal: halfway between its vertices
    half = gaps / 2
    edges = np.stack([np.where(used, np.cos(mid), 0.0), np.where(used, np.sin(mid), 0.0),
                      np.where(used, np.cos(half), 1.0)], axis=-1)
    area = (0.5 * np.sin(gaps) * used).sum(axis=1)
    return edges, k, area


def _draw_shapes(seed, height, width, options) -> _Shapes:
    """Shapes until their summed area reaches ``coverage`` times the area
    their centres are spread over; sorted nearest first."""
    rng = np.random.default_rng([seed, 1])
    target = options.coverage * (1.2 * width) * (1.2 * height)
    parts, total = [], 0.0
    while total < target:
        batch, area = _draw_batch(rng, 1024, height, width, options)
        cum = total + np.cumsum(area)
        keep = int(np.searchsorted(cum, target)) + 1
        parts.append({k: v[:keep] for k, v in batch.items()})
        total = float(cum[min(keep, len(cum)) - 1])
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    cat["depth"] = _f32_within(cat["depth"], *options.depth_range_m)
    geo = _geometry(cat)
    order = np.argsort(cat["depth"], kind="stable")
    return _Shapes(kind=cat["kind"][order], depth=cat["depth"][order], n_edges=cat["n_edges"][order],
                   **{k: v[order] for k, v in geo.items()})


def _geometry(d):
    """The inside test's float32 parameters and the bounding half-extents
    (px) from centre, rotation, half-axes a, b and unit-circle polygon
    edges (nx, ny, d)."""
    c, s, a, b = d["cos"], d["sin"], d["a"], d["b"]
    pu, pv, qu, qv = c / a, s / a, -s / b, c / b
    nx, ny = d["edges"][..., 0], d["edges"][..., 1]
    edges = np.stack([nx * pu[:, None] + ny * qu[:, None], nx * pv[:, None] + ny * qv[:, None],
                      d["edges"][..., 2]], axis=-1)
    is_box = np.isin(d["kind"], [SHAPE_KINDS.index(k) for k in ("rectangle", "bar", "line")])
    ext_x = np.where(is_box, a * np.abs(c) + b * np.abs(s), np.sqrt((a * c) ** 2 + (b * s) ** 2))
    ext_y = np.where(is_box, a * np.abs(s) + b * np.abs(c), np.sqrt((a * s) ** 2 + (b * c) ** 2))
    f = np.float32
    return dict(cx=d["cx"].astype(f), cy=d["cy"].astype(f), pu=pu.astype(f), pv=pv.astype(f), qu=qu.astype(f),
                qv=qv.astype(f), edges=edges.astype(f), ext_x=ext_x, ext_y=ext_y)


def leaves_layers(seed: int, height: int, width: int, options: LeavesOptions = LeavesOptions()) -> list[Layer]:
    """The layers of :func:`leaves_rgbd`'s frame for the same arguments,
    nearest first, the background last: ``depth[i, j]`` is the
    ``depth_m`` of the first layer that covers ``(j + 0.5, i + 0.5)``."""
    _check_call(seed, height, width, options, None)
    sh = _draw_shapes(seed, height, width, options)
    layers = []
    for i in range(len(sh)):
        k = int(sh.n_edges[i]) if SHAPE_KINDS[sh.kind[i]] == "polygon" else 0
        layers.append(Layer(index=i, kind=SHAPE_KINDS[sh.kind[i]], depth_m=float(sh.depth[i]),
                            centre_px=(float(sh.cx[i]), float(sh.cy[i])), p_row=(float(sh.pu[i]), float(sh.pv[i])),
                            q_row=(float(sh.qu[i]), float(sh.qv[i])),
                            edges=tuple(tuple(float(v) for v in e) for e in sh.edges[i, :k])))
    layers.append(Layer(index=len(sh), kind=BACKGROUND, depth_m=_far_depth(options)))
    return layers


# ----------------------------------------------------------------------------------------------------------------
# rasterising


def _grid_boxes(sh: _Shapes, gh: int, gw: int):
    """Each shape's bounding box in grid indices [r0, r1) x [c0, c1),
    clipped to the grid, with a grid point of margin."""
    c0 = np.clip(np.floor(2 * (sh.cx - sh.ext_x)) - 1, 0, gw).astype(np.int64)
    c1 = np.clip(np.ceil(2 * (sh.cx + sh.ext_x)) + 2, 0, gw).astype(np.int64)
    r0 = np.clip(np.floor(2 * (sh.cy - sh.ext_y)) - 1, 0, gh).astype(np.int64)
    r1 = np.clip(np.ceil(2 * (sh.cy + sh.ext_y)) + 2, 0, gh).astype(np.int64)
    return r0, r1, c0, c1


def _params(sh: _Shapes, i):
    """The inside test's parameters of shape i (an index: scalars) or of
    the shapes i (an index array: shaped (K, 1, 1), edges (K, 1, 1, k))."""
    if np.ndim(i) == 0:
        k = int(sh.n_edges[i])
        e = sh.edges[i, :k]
        return sh.cx[i], sh.cy[i], sh.pu[i], sh.pv[i], sh.qu[i], sh.qv[i], e[:, 0], e[:, 1], e[:, 2]
    col = (slice(None), None, None)
    e = sh.edges[i, :int(sh.n_edges[i].max())][:, None, None]
    return (sh.cx[i][col], sh.cy[i][col], sh.pu[i][col], sh.pv[i][col], sh.qu[i][col], sh.qv[i][col],
            e[..., 0], e[..., 1], e[..., 2])


def _rasterise(sh: _Shapes, height: int, width: int) -> np.ndarray:
    """The layer index (int32, the background = len(sh)) at every point of
    the half-pixel grid, (2H + 1, 2W + 1): the nearest layer covering it.
    Large shapes first, nearest first, each on its box (skipped where
    nearer ones hide it all); then the small ones in batches."""
    gh, gw = 2 * height + 1, 2 * width + 1
    buf = np.full((gh, gw), len(sh), dtype=np.int32)
    r0, r1, c0, c1 = _grid_boxes(sh, gh, gw)
    side = np.maximum(r1 - r0, c1 - c0)
    visible = (r1 > r0) & (c1 > c0)
    family = np.array([_FAMILY[k] for k in SHAPE_KINDS])[sh.kind]
    sides = [s for s in _BATCH_SIDES if s <= min(gh, gw)]     # a batch's blocks lie inside the grid
    half = np.float32(0.5)
    for i in np.flatnonzero(visible & (side > sides[-1])):
        view = buf[r0[i]:r1[i], c0[i]:c1[i]]
        if view.max() < i:
            continue
        y = (np.arange(r0[i], r1[i], dtype=np.float32) * half)[:, None]
        x = (np.arange(c0[i], c1[i], dtype=np.float32) * half)[None, :]
        np.minimum(view, np.int32(i), out=view, where=_inside(family[i], *_params(sh, i), x, y))
    lower = 0
    for s in sides:
        in_bucket = visible & (side > lower) & (side <= s)
        for fam in ("ellipse", "box", "polygon"):
            sel = np.flatnonzero(in_bucket & (family == fam))
            if sel.size:
                _rasterise_batch(buf, sh, sel, fam, s, np.minimum(r0[sel], gh - s), np.minimum(c0[sel], gw - s))
        lower = s
    return buf


def _rasterise_batch(buf, sh, sel, family, s, r0, c0):
    """Small shapes at once, each on the s x s block of grid points from
    (r0, c0) that holds its box: those hidden by nearer shapes already
    drawn are dropped, the rest tested; the z-buffer keeps the smallest
    index per point."""
    gw = buf.shape[1]
    o = np.arange(s, dtype=np.int32)
    rows = r0.astype(np.int32)[:, None] + o          # (K, s)
    cols = c0.astype(np.int32)[:, None] + o
    index = (rows * np.int32(gw))[:, :, None] + cols[:, None, :]
    flat = buf.reshape(-1)
    seen = flat[index].max(axis=(1, 2)) > sel
    if not seen.all():
        sel, rows, cols, index = sel[seen], rows[seen], cols[seen], index[seen]
        if not sel.size:
            return
    half = np.float32(0.5)
    inside = _inside(family, *_params(sh, sel), (cols.astype(np.float32) * half)[:, None, :],
                     (rows.astype(np.float32) * half)[:, :, None])
    ids = np.broadcast_to(sel.astype(np.int32)[:, None, None], inside.shape)
    np.minimum.at(flat, index[inside], ids[inside])


# ----------------------------------------------------------------------------------------------------------------
# procedural textures


class _Noise:
    """Periodic fractal noise of one tile size, zero mean, unit deviation:
    three fields made per frame by spectral synthesis (random phases,
    amplitude ~ f ** -beta, beta 0.6, 1.1, 1.6); a field asked for is the
    one of nearest beta, rolled, flipped and transposed at random (all
    seamless on a periodic tile)."""
    BETAS = (0.6, 1.1, 1.6)

    def __init__(self, rng, size):
        self.rng = rng
        self.size = size
        f = np.hypot(np.fft.fftfreq(size)[:, None], np.fft.rfftfreq(size)[None, :])
        f[0, 0] = 1.0
        shape = f.shape
        self.fields = []
        for beta in self.BETAS:
            amp = f ** -beta
            amp[0, 0] = 0.0
            spec = amp * (rng.standard_normal(shape, dtype=np.float32)
                          + 1j * rng.standard_normal(shape, dtype=np.float32))
            x = np.fft.irfft2(spec, s=(size, size))
            self.fields.append(((x - x.mean()) / x.std()).astype(np.float32))
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        self.yy, self.xx = yy, xx

    def field(self, beta):
        x = self.fields[int(np.argmin([abs(beta - b) for b in self.BETAS]))]
        x = np.roll(x, tuple(self.rng.integers(self.size, size=2)), axis=(0, 1))
        if self.rng.random() < 0.5:
            x = x.T
        return x[::-1] if self.rng.random() < 0.5 else x


def _tile(kind, rng, noise: _Noise) -> np.ndarray:
    """One periodic texture tile (T, T) float32 in [0, 1]: the pattern, with
    fractal grain on top so that every tile has detail down to a texel."""
    t = noise.size
    yy, xx = noise.yy, noise.xx
    if kind == "noise":
        v = 0.5 + rng.uniform(0.15, 0.3) * noise.field(rng.uniform(0.9, 1.6))
    elif kind == "stripes":
        k1, k2 = rng.integers(-12, 13, 2)
        if k1 == 0 and k2 == 0:
            k1 = 6
        phase = 2 * np.pi * (k1 * xx + k2 * yy) / t + rng.uniform(0, 2.5) * noise.field(1.6)
        sharp = rng.uniform(1.0, 8.0)
        v = 0.5 + 0.5 * np.tanh(sharp * (np.sin(phase) + rng.uniform(-0.5, 0.5))) / np.tanh(sharp)
    elif kind in ("checker", "cells", "bricks"):
        n = int(2 ** rng.integers(2, 6))            # cells a side
        p = t // n
        row = (yy // p).astype(np.int64)
        shift = (row % 2) * (p // 2) if kind == "bricks" else 0
        col = ((xx + shift) // p).astype(np.int64) % n
        if kind == "checker":
            v = ((row + col) % 2).astype(np.float32) * rng.uniform(0.5, 1.0) + rng.uniform(0.0, 0.3)
        else:
            v = rng.uniform(0.2, 1.0, (n, n)).astype(np.float32)[row, col]
        if kind != "cells":
            mortar = rng.uniform(0.0, 0.15) * p
            du = np.minimum((xx + shift) % p, p - (xx + shift) % p)
            dv = np.minimum(yy % p, p - yy % p)
            v = np.where(np.minimum(du, dv) < mortar, rng.uniform(0.0, 0.4), v)
    elif kind == "dots":
        n = int(2 ** rng.integers(2, 6))
        p = t / n
        jitter = rng.uniform(-0.25, 0.25, (2, n, n)) * p
        gi, gj = (yy // p).astype(np.int64), (xx // p).astype(np.int64)
        dy = yy - ((gi + 0.5) * p + jitter[0][gi, gj])
        dx = xx - ((gj + 0.5) * p + jitter[1][gi, gj])
        radius = rng.uniform(0.12, 0.3) * p * (1 + 0.3 * noise.field(2.0))
        v = np.clip(radius - np.hypot(dx, dy) + 0.5, 0.0, 1.0) * rng.uniform(0.5, 1.0)
    elif kind == "rings":
        n = int(rng.integers(2, 10))
        k1, k2 = rng.integers(0, 3, 2)
        base = 2 * np.pi * (n * xx + k1 * yy) / t if rng.random() < 0.5 else \
            2 * np.pi * n * (np.sin(2 * np.pi * (xx + k2 * yy) / t) + np.sin(2 * np.pi * yy / t))
        v = 0.5 + 0.5 * np.sin(base + rng.uniform(1.0, 6.0) * noise.field(1.4))
    else:
        raise ValueError(kind)
    grain = rng.uniform(0.1, 0.4)
    v = (1 - grain) * v + grain * (0.5 + 0.3 * noise.field(rng.uniform(0.4, 1.0)))
    return np.clip(v, 0.0, 1.0).astype(np.float32)


# ----------------------------------------------------------------------------------------------------------------
# user textures


_photo_cache: OrderedDict = OrderedDict()
caches.register("texture photographs", _photo_cache.clear, lambda: len(_photo_cache))


def _photo(path) -> np.ndarray:
    """A user image as float32 linear RGB in [0, 1], box-reduced by a whole
    factor to at most _PHOTO_MAX_SIDE_PX a side; kept for later frames."""
    st = path.stat()
    key = (str(path), st.st_mtime_ns, st.st_size)
    if key in _photo_cache:
        _photo_cache.move_to_end(key)
        return _photo_cache[key]
    from ..io.images import read_image
    img = read_image(path)
    f = max(1, math.ceil(max(img.shape[:2]) / _PHOTO_MAX_SIDE_PX))
    if f > 1:
        h, w = img.shape[0] // f * f, img.shape[1] // f * f
        img = img[:h, :w].reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
    img = np.ascontiguousarray(np.clip(img, 0.0, 1.0), dtype=np.float32)
    _photo_cache[key] = img
    while len(_photo_cache) > _PHOTO_CACHE_SIZE:
        _photo_cache.popitem(last=False)
    return img


# ----------------------------------------------------------------------------------------------------------------
# colour


def _hsv_to_rgb(h, s, v):
    k = np.stack([(5 + h * 6) % 6, (3 + h * 6) % 6, (1 + h * 6) % 6], axis=-1)
    return v[:, None] * (1 - s[:, None] * np.clip(np.minimum(k, 4 - k), 0, 1))


def _colours(rng, n, options):
    """Each layer's two colours (n, 3) linear: the texture runs from the
    first to the second."""
    lo, hi = options.albedo_range
    value = lo * (hi / lo) ** rng.random(n)
    sat = np.where(rng.random(n) < 0.3, rng.uniform(0.0, 0.15, n), rng.uniform(0.2, 0.85, n))
    hue = rng.random(n)
    c0 = _hsv_to_rgb(hue, sat, value)
    other_hue = np.where(rng.random(n) < 0.35, rng.random(n), hue + rng.normal(0, 0.03, n))
    c1 = _hsv_to_rgb(other_hue % 1.0, sat * rng.uniform(0.5, 1.2, n).clip(0, 1),
                     value * np.exp(rng.uniform(math.log(0.15), 0.0, n)))
    return c0, c1


def _texture_map(rng, n, cx, cy, scale_half_extent, height, width, options, period):
    """Per layer: the affine map from pixel (x, y) to texel (u, v) with u, v
    >= 0 over the frame, and the shading plane s0 + sx x + sy y."""
    lo, hi = options.texel_per_px
    k = lo * (hi / lo) ** rng.random(n)
    phi = rng.uniform(0.0, 2 * math.pi, n)
    au, bu = k * np.cos(phi), k * np.sin(phi)
    av, bv = -k * np.sin(phi), k * np.cos(phi)
    ou, ov = rng.uniform(0, period, n), rng.uniform(0, period, n)
    cu = ou - (au * cx + bu * cy)
    cv = ov - (av * cx + bv * cy)
    cu, cv = _lift(au, bu, cu, av, bv, cv, height, width, period, period)
    # shading as if lit from one side: a plane over the shape, 0.2 to 1.15 of the colour inside it
    s_mid = rng.uniform(0.55, 0.85, n)
    slope = rng.uniform(0.0, 0.3, n) / scale_half_extent / math.sqrt(2)
    theta = rng.uniform(0.0, 2 * math.pi, n)
    sx, sy = slope * np.cos(theta), slope * np.sin(theta)
    s0 = s_mid - sx * cx - sy * cy
    return np.stack([au, bu, cu, av, bv, cv, s0, sx, sy], axis=1)


def _lift(au, bu, cu, av, bv, cv, height, width, period_u, period_v):
    """The offsets cu, cv raised by whole periods so that u, v >= 0 over the
    frame (texel lookups truncate, and wrap with a mask or a mirror)."""
    corners_x, corners_y = np.array([0.0, width, 0.0, width]), np.array([0.0, 0.0, height, height])
    umin = (au[:, None] * corners_x + bu[:, None] * corners_y).min(axis=1) + cu
    vmin = (av[:, None] * corners_x + bv[:, None] * corners_y).min(axis=1) + cv
    return (cu + period_u * np.ceil(np.maximum(0.0, -umin) / period_u + 1),
            cv + period_v * np.ceil(np.maximum(0.0, -vmin) / period_v + 1))


def _render(buf, table, tiles, photos, photo_of, height, width):
    """The image (H, W, 3) float32: colour at every grid point from its
    layer's texture map, integrated over each pixel (:func:`_integrate`),
    a band of pixel rows at a time so that the work stays in cache."""
    gw = buf.shape[1]
    cols = [np.ascontiguousarray(table.map[:, k]) for k in range(9)]
    c0 = [np.ascontiguousarray(table.c0[:, k]) for k in range(3)]
    dc = [np.ascontiguousarray(table.dc[:, k]) for k in range(3)]
    t = tiles.shape[1]
    flat_tiles = tiles.reshape(-1)
    out = np.empty((3, height, width), dtype=np.float32)
    x = (np.arange(gw, dtype=np.float32) * np.float32(0.5))[None, :]
    band = max(1, (1 << 15) // gw)                       # pixel rows per band
    for i0 in range(0, height, band):
        i1 = min(height, i0 + band)
        lay = buf[2 * i0:2 * i1 + 1]
        y = (np.arange(2 * i0, 2 * i1 + 1, dtype=np.float32) * np.float32(0.5))[:, None]
        au, bu, cu, av, bv, cv, s0, sx, sy = (np.take(c, lay) for c in cols)
        u = au * x + bu * y + cu
        v = av * x + bv * y + cv
        shade = s0 + sx * x + sy * y
        idx = np.take(table.tile_base, lay) + (v.astype(np.int32) & (t - 1)) * t + (u.astype(np.int32) & (t - 1))
        tex = np.take(flat_tiles, idx)
        rgb = [(np.take(c0[k], lay) + np.take(dc[k], lay) * tex) * shade for k in range(3)]
        if photos:
            _paint_photos(rgb, np.take(photo_of, lay), photos, u, v, shade)
        for k in range(3):
            out[k, i0:i1] = _integrate(rgb[k])
    return np.ascontiguousarray(out.transpose(1, 2, 0))


def _paint_photos(rgb, which, photos, u, v, shade):
    """Overwrite the points of photo-textured layers with their image's
    texel (mirrored at its borders) times the shading."""
    for j, img in enumerate(photos):
        sel = which == j
        if sel.any():
            h, w = img.shape[:2]
            texel = img[_mirror(v[sel].astype(np.int32), h), _mirror(u[sel].astype(np.int32), w)]
            s = shade[sel]
            for k in range(3):
                rgb[k][sel] = texel[:, k] * s


def _mirror(i, n):
    """Texel index i >= 0 folded into [0, n) by mirrored repeats (seamless)."""
    i = i % (2 * n)
    return np.where(i >= n, 2 * n - 1 - i, i)


def _integrate(grid):
    """Each pixel's mean over its square from the half-pixel grid points
    (2h + 1, 2w + 1) it spans, by the trapezoidal rule (weights 1/4, 1/2,
    1/4 on each axis): (h, w)."""
    q, h = np.float32(0.25), np.float32(0.5)
    rows = q * grid[0:-1:2] + h * grid[1::2] + q * grid[2::2]
    return q * rows[:, 0:-1:2] + h * rows[:, 1::2] + q * rows[:, 2::2]


@dataclass
class _Table:
    """Per-layer colour parameters, indexed by layer (the background last)."""
    map: np.ndarray          # (n, 9) float32: au bu cu av bv cv s0 sx sy
    tile_base: np.ndarray    # (n,) int32: offset of the layer's tile in the flattened tiles
    c0: np.ndarray           # (n, 3) float32
    dc: np.ndarray           # (n, 3) float32


def _textures(seed, sh: _Shapes, height, width, options, textures):
    """The procedural tiles, the user images in use, and every layer's
    colour parameters; plus what the info record says about them."""
    rng = np.random.default_rng([seed, 2])
    noise = _Noise(rng, options.tile_px)
    kinds = [TILE_KINDS[i] for i in rng.integers(len(TILE_KINDS), size=options.tiles)]
    tiles = np.stack([_tile(k, rng, noise) for k in kinds])
    n = len(sh) + 1
    cx = np.append(sh.cx, width / 2)
    cy = np.append(sh.cy, height / 2)
    extent = np.append(np.maximum(sh.ext_x, sh.ext_y), math.hypot(width, height) / 2)
    tile_of = rng.integers(options.tiles, size=n)
    c0, c1 = _colours(rng, n, options)
    table = _Table(map=_texture_map(rng, n, cx, cy, extent, height, width, options, options.tile_px)
                   .astype(np.float32), tile_base=(tile_of * options.tile_px ** 2).astype(np.int32),
                   c0=c0.astype(np.float32), dc=(c1 - c0).astype(np.float32))
    photo_of = np.full(n, -1, dtype=np.int8)
    photos, names = [], []
    if textures is not None:
        prng = np.random.default_rng([seed, 3])
        picked = [textures.pick(prng) for _ in range(min(_PHOTOS_PER_FRAME, len(textures.sets)))]
        uses = np.where(prng.random(n) < options.photo_share, prng.integers(len(picked), size=n), -1)
        for j, s in enumerate(picked):
            if s.name in names or not (uses == j).any():
                continue
            photo_of[uses == j] = len(photos)
            photos.append(_photo(s.colour))
            names.append(s.name)
        # a photograph turns by quarter turns and flips, and is never recoloured
        is_photo = photo_of >= 0
        if is_photo.any():
            size_wh = np.array([(p.shape[1], p.shape[0]) for p in photos], dtype=np.float64)[photo_of[is_photo]]
            table.map[is_photo] = _photo_map(prng, int(is_photo.sum()), cx[is_photo], cy[is_photo],
                                             extent[is_photo], height, width, options, table.map[is_photo],
                                             size_wh)
    info = {"procedural_tiles": kinds, "textures": sorted(names),
            "photo_layers": int((photo_of >= 0).sum())}
    return tiles, table, photos, photo_of, info


def _photo_map(rng, n, cx, cy, extent, height, width, options, current, size_wh):
    """Texel maps of photo-textured layers: a random scale, quarter turn and
    flip, a random crop offset; the shading plane is kept but brightened,
    so a photograph keeps its colour (0.6 to 1 of it)."""
    lo, hi = options.texel_per_px
    k = lo * (hi / lo) ** rng.random(n)
    turn = rng.integers(4, size=n)
    flip = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    c = np.array([1.0, 0.0, -1.0, 0.0])[turn]
    s = np.array([0.0, 1.0, 0.0, -1.0])[turn]
    au, bu = k * c * flip, k * s * flip
    av, bv = -k * s, k * c
    cu = rng.uniform(0, 2 * size_wh[:, 0]) - (au * cx + bu * cy)
    cv = rng.uniform(0, 2 * size_wh[:, 1]) - (av * cx + bv * cy)
    cu, cv = _lift(au, bu, cu, av, bv, cv, height, width, 2 * size_wh[:, 0], 2 * size_wh[:, 1])
    out = current.copy()
    out[:, :6] = np.stack([au, bu, cu, av, bv, cv], axis=1)
    # shade: 0.6 to 1.0 over the shape
    mid = rng.uniform(0.75, 0.85, n)
    slope = rng.uniform(0.0, 0.15, n) / extent / math.sqrt(2)
    theta = rng.uniform(0.0, 2 * math.pi, n)
    sx, sy = slope * np.cos(theta), slope * np.sin(theta)
    out[:, 6:9] = np.stack([mid - sx * cx - sy * cy, sx, sy], axis=1)
    return out


# ----------------------------------------------------------------------------------------------------------------
# the frame


def _check_call(seed, height, width, options, textures):
    for name, v in (("height", height), ("width", width)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not 4 <= v <= MAX_SIDE_PX:
            raise InputRangeError(name, v, f"an integer 4 to {MAX_SIDE_PX} px")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise InputRangeError("seed", seed, "an integer >= 0")
    if not isinstance(options, LeavesOptions):
        raise InputRangeError("options", type(options).__name__, "a LeavesOptions")
    if textures is not None:
        from .textures import TextureLibrary
        if not isinstance(textures, TextureLibrary) or not textures.sets:
            raise InputRangeError("textures", type(textures).__name__, "None or a TextureLibrary with a set")


def leaves_rgbd(seed: int, height: int, width: int, options: LeavesOptions = LeavesOptions(),
                textures=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """A dead-leaves frame: ``(image, depth, info)``.

    ``image``: float32 (H, W, 3) linear RGB, anti-aliased (each pixel the
    mean over its square); ``depth``: float32 (H, W) metres, planar, each
    pixel exactly the depth of the layer covering its centre
    (:func:`leaves_layers`); ``info``: a JSON-able record (counts of
    layers, shapes by kind and visible layers, the depth range, the
    procedural tiles and the user texture sets used by name).

    ``textures`` (a :class:`~dcdi_core.dataset.textures.TextureLibrary`, or
    None): then about ``options.photo_share`` of the layers take their
    texture from up to four of its sets' colour images (scaled, turned by
    quarter turns, flipped, mirrored at their borders; colour kept).
    Raises InputRangeError for a side under 4 px or bad arguments, before
    any work."""
    _check_call(seed, height, width, options, textures)
    sh = _draw_shapes(seed, height, width, options)
    buf = _rasterise(sh, height, width)
    depths = np.append(sh.depth, _far_depth(options)).astype(np.float32)
    centre = buf[1::2, 1::2]
    depth = depths[centre]
    tiles, table, photos, photo_of, tex_info = _textures(seed, sh, height, width, options, textures)
    image = _render(buf, table, tiles, photos, photo_of, height, width)
    kinds, counts = np.unique(sh.kind, return_counts=True)
    info = {
        "layers": len(sh) + 1,
        "shapes": len(sh),
        "shape_kinds": {SHAPE_KINDS[k]: int(c) for k, c in zip(kinds, counts)},
        "visible_layers": int(np.count_nonzero(np.bincount(centre.reshape(-1), minlength=len(sh) + 1))),
        "depth_range_m": [float(v) for v in options.depth_range_m],
        "background_depth_m": float(depths[-1]),
        **tex_info,
    }
    return image, depth, info
