"""Multi-resolution blur: a wide kernel convolved at 1/2, 1/4 or 1/8 of the resolution.

A kernel several pixels wide removes the image's high frequencies, so the
part of an image (a bokeh depth layer, a region of the plain blur) whose
kernels are all wide can be blurred on a coarser grid and brought back:

1. the input (the layer's premultiplied colour and its coverage) is area
   averaged over f x f blocks (f = 2^s, s the level);
2. the PSF map is made on the coarse grid directly: a geometry with the
   pitch f p whose pixel centres are the blocks' centres on the sensor
   (fine pixel f u + (f - 1) / 2), patches of ``coarse_patch`` coarse pixels
   (so f^2 fewer kernels than at full resolution for the same patch size),
   each kernel the library's at the patch's field, azimuth and depth (the
   mean inverse depth of its valid pixels), then area-resampled to the
   coarse pitch (``psf.pitch.area_resample``: exact, sum kept);
3. ``patch_convolve`` runs there, and the result (block means of the
   blurred image) is brought back to full resolution: converted to point
   values at the block centres (fine f u + (f - 1) / 2), then Keys' cubic
   interpolation, edges clamped (the sum is kept; the final image is
   clamped to >= 0, which adds up to ~3 % of an isolated bright disc's
   energy where the cubic rings below 0 at its rim).

Every step keeps a constant a constant (block means, kernels that sum to 1,
tents that sum to 1, interpolation weights that sum to 1).

The level rule: s is the largest level <= ``max_level`` for which the
narrowest kernel's radius (of the disk about the kernel centre that holds
all but ``LEVEL_EPS`` = half of every channel's energy,
``psfmap.support_radius``) is >= ``c`` 2^s fine pixels; ``c`` is the
tolerance (larger: finer levels, closer to the exact path). The radius of
a patch's kernel is bounded below by the smallest radius among the four
library kernels it is interpolated from (:func:`patch_radius`); a bokeh
layer takes the level of its narrowest patch.

What this does not share: the forward transform of the image across the
bokeh's layers (each layer's input is the image masked differently, so
each has its own transforms).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputRangeError
from ..psf.pitch import area_resample, resampled_size
from . import fft
from .convolve import ConvolveOptions, box_reach, patch_box, patch_convolve
from .psfmap import psf_map, support_radius
from .base import check_patch

# the level rule reads the disk holding half the energy: the core's width. 6P's
# defocus kernels are a peaked core in a wide halo, and a rule on the 90 %
# radius sent such kernels to 1/2, where the core was lost
LEVEL_EPS = 0.5
# the rule `dcdi bench render` times: BokehOptions' default stays the exact path
# (multires None): at 1280 x 1920 no rule was both faster and as close at the
# depth edge (report simulation-accuracy's multi-resolution table, docs/performance.md)
BENCH_C = 4.0
DEFAULT_MAX_LEVEL = 2      # at most 1/4 of the resolution


def check_multires(c, max_level, coarse_patch) -> None:
    """Refuse a level rule that means nothing, before any work."""
    if c is not None and (isinstance(c, bool) or not isinstance(c, (int, float, np.integer, np.floating))
                          or not math.isfinite(c) or c <= 0):
        raise InputRangeError("multires (level rule c, px)", c,
                              "a finite number > 0 (level s where the kernels' radius >= c 2^s px), or None "
                              "for the exact path")
    if isinstance(max_level, bool) or not isinstance(max_level, (int, np.integer)) or not 0 <= max_level <= 4:
        raise InputRangeError("max_level", max_level, "an integer in [0, 4] (1/16 of the resolution at most)")
    if isinstance(coarse_patch, bool) or not isinstance(coarse_patch, (int, np.integer)) or coarse_patch < 2 \
            or coarse_patch % 2:
        raise InputRangeError("coarse_patch", coarse_patch, "an even number of coarse pixels >= 2")


@dataclass(frozen=True)
class MultiresOptions:
    """How :func:`grouped_blur` and :func:`plain_blur` blur, checked when made.

    c: the level rule's tolerance (px, > 0; None: every patch at level 0):
    a patch goes to the largest level s <= ``max_level`` (0 to 4) whose
    kernels' ``LEVEL_EPS`` radius is >= c 2^s px. patch: the full-resolution
    patch size m (px, even, >= 2); coarse_patch: the patch size at the
    coarser levels (coarse px, even, >= 2). fft_backend: 'scipy' or 'numpy'
    (None: the fastest installed). ``BokehOptions.multires_options`` makes
    one from a bokeh's options.
    """

    c: float | None
    patch: int = 16
    max_level: int = DEFAULT_MAX_LEVEL
    coarse_patch: int = 16
    fft_backend: str | None = None

    def __post_init__(self):
        check_multires(self.c, self.max_level, self.coarse_patch)
        check_patch(self.patch)
        fft.backend(self.fft_backend)                     # its own message: the backends this Python has


def level_for(radius_px, c: float | None, max_level: int) -> np.ndarray:
    """The level s (0 = full resolution) for kernels of ``radius_px``: the
    largest s <= max_level with radius >= c 2^s; 0 where c is None."""
    r = np.asarray(radius_px, np.float64)
    if c is None or max_level == 0:
        return np.zeros(r.shape, np.int64)
    s = np.floor(np.log2(np.maximum(r, 1e-12) / c))
    return np.clip(s, 0, max_level).astype(np.int64)


def radius_table(library) -> np.ndarray:
    """The ``LEVEL_EPS`` radius (px) of each of the library's kernels:
    (depth bins, fields), inf for bins not computed."""
    table = np.full(library.psf.shape[:2], np.inf)
    comp = np.flatnonzero(library.computed)
    if comp.size:
        table[comp] = support_radius(library.psf[comp], LEVEL_EPS)
    return table


def patch_radius(library, table: np.ndarray, field, depth_m) -> np.ndarray:
    """A lower bound of the ``LEVEL_EPS`` radius (px) of the kernel at each
    (field, depth) (broadcast; depth > 0 m or inf): the smallest radius
    among the library kernels it is interpolated from."""
    field, depth_m = np.broadcast_arrays(np.asarray(field, float), np.asarray(depth_m, float))
    i0, i1, t = library.depth_bins(depth_m, clamp_near=True)
    j0, j1, u = library.field_weights(np.minimum(field, 1.0))
    big = np.inf
    r = np.full(field.shape, big)
    for ii, jj, wgt in ((i0, j0, (1 - t) * (1 - u)), (i0, j1, (1 - t) * u), (i1, j0, t * (1 - u)), (i1, j1, t * u)):
        r = np.minimum(r, np.where(wgt > 0, table[ii, jj], big))
    return r


def patch_levels(library, table, geometry, depth: np.ndarray, valid: np.ndarray, m: int, c, max_level: int):
    """Per m x m patch of an image on ``geometry``: (level (nph, npw) int,
    has (nph, npw) bool: the patch has valid pixels), the level from the
    narrowest kernel its depth (mean inverse depth of its ``valid``
    pixels) interpolates from."""
    from .psfmap import patch_inverse_depth
    h, w = depth.shape
    inv, has = patch_inverse_depth(np.where(valid, depth, np.nan), m, library.grid.far_m)
    nph, npw = has.shape
    rows = np.minimum(np.arange(nph) * m + (m - 1) / 2.0, h - 1)
    cols = np.minimum(np.arange(npw) * m + (m - 1) / 2.0, w - 1)
    field = geometry.field(rows[:, None], cols[None, :])
    d = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    radius = np.where(has, patch_radius(library, table, field, d), np.inf)
    return level_for(radius, c, max_level), has


def block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """Means over f x f blocks of a (H, W, C) with H, W multiples of f."""
    h, w, c = a.shape
    return a.reshape(h // f, f, w // f, f, c).mean(axis=(1, 3), dtype=np.float32)


def pad_to(a: np.ndarray, f: int) -> np.ndarray:
    """``a`` (H, W, ...) edge-padded at the bottom and right to multiples of f."""
    h, w = a.shape[:2]
    ph, pw = -h % f, -w % f
    if ph == 0 and pw == 0:
        return a
    return np.pad(a, ((0, ph), (0, pw)) + ((0, 0),) * (a.ndim - 2), mode="edge")


def coarse_geometry(geometry, f: int, hc: int, wc: int):
    """The geometry of the f x f block grid of ``geometry`` (hc x wc blocks):
    pitch f p, block u's centre at fine pixel f u + (f - 1) / 2."""
    cy, cx = geometry.center_px
    return replace(geometry, height=hc, width=wc, pixel_pitch_mm=geometry.pixel_pitch_mm * f,
                   center_px=((cy - (f - 1) / 2.0) / f, (cx - (f - 1) / 2.0) / f))


def coarse_depth(depth: np.ndarray, valid: np.ndarray, far_m: float, f: int) -> np.ndarray:
    """The depth (m) of each f x f block: its valid pixels' mean inverse depth
    (inf for 0 diopters), NaN where it has none. depth, valid (H, W) with
    H, W multiples of f."""
    inv = np.where(valid & (depth < far_m), 1.0 / np.where(valid, depth, 1.0), 0.0)
    h, w = depth.shape
    s = inv.reshape(h // f, f, w // f, f).sum(axis=(1, 3))
    n = valid.reshape(h // f, f, w // f, f).sum(axis=(1, 3))
    mean = s / np.maximum(n, 1)
    return np.where(n > 0, np.where(mean > 0, 1.0 / np.where(mean > 0, mean, 1.0), np.inf), np.nan)


UPSAMPLING = ("linear", "cubic")


def _keys(t: float) -> tuple[float, float, float, float]:
    """Keys' cubic (a = -1/2) weights of the samples at -1, 0, 1, 2 for a point t in [0, 1)."""
    a = -0.5

    def k(x):
        x = abs(x)
        if x < 1:
            return (a + 2) * x ** 3 - (a + 3) * x ** 2 + 1
        if x < 2:
            return a * x ** 3 - 5 * a * x ** 2 + 8 * a * x - 4 * a
        return 0.0
    return k(t + 1), k(t), k(1 - t), k(2 - t)


def upsample(c: np.ndarray, f: int, h: int, w: int, method: str = "linear", averages: bool = False) -> np.ndarray:
    """Interpolation of a coarse (hc, wc, C) grid, whose sample u sits at fine
    pixel f u + (f - 1) / 2, onto the fine (h, w) pixels (h <= f hc, w <= f wc);
    beyond the outer samples the edge value (clamped). method: 'linear'
    (bilinear) or 'cubic' (Keys, a = -1/2). averages: the samples are f x f
    block means, converted first to point values at the block centres
    (v - (v[u-1] - 2 v + v[u+1]) / 24 per axis, exact for quadratics).
    Every set of weights sums to 1: a constant stays a constant."""
    if method not in UPSAMPLING:
        raise InputRangeError("upsampling", method, " or ".join(UPSAMPLING))
    if f == 1:
        return c[:h, :w]

    def along(a, axis):
        n = a.shape[axis]
        pad = 2 if method == "cubic" else 1
        ap = np.concatenate([np.take(a, [0] * pad, axis), a, np.take(a, [n - 1] * pad, axis)], axis=axis)

        def sl(start):
            idx = [slice(None)] * a.ndim
            idx[axis] = slice(pad + start, pad + start + n)
            return ap[tuple(idx)]
        if averages:
            a = a - (sl(-1) - 2 * a + sl(1)) * np.float32(1 / 24)
            ap = np.concatenate([np.take(a, [0] * pad, axis), a, np.take(a, [n - 1] * pad, axis)], axis=axis)
        parts = []
        for p in range(f):
            d = (p - (f - 1) / 2.0) / f                # offset of fine phase p from its block centre, in blocks
            lo = -1 if d < 0 else 0                    # the sample below: block u + lo
            t = d - lo                                 # in [0, 1) from it
            if method == "linear":
                parts.append(np.float32(1 - t) * sl(lo) + np.float32(t) * sl(lo + 1))
            else:
                wts = _keys(t)
                acc = np.float32(wts[0]) * sl(lo - 1)
                for j in range(1, 4):
                    acc += np.float32(wts[j]) * sl(lo - 1 + j)
                parts.append(acc)
        out = np.stack(parts, axis=axis + 1)           # (..., n, f, ...) -> (..., n f, ...)
        shape = list(a.shape)
        shape[axis] = n * f
        return out.reshape(shape)

    rows = along(c, 0)[:h]
    return along(rows, 1)[:, :w]


def coarse_blur(image: np.ndarray, depth: np.ndarray, valid: np.ndarray, library, geometry, f: int,
                coarse_patch: int, *, pairs=None, keep_range_m=None, fallback_valid=None, fft_backend=None,
                upsampling: str = "cubic"):
    """Patch-wise blur of ``image`` (H, W, C) on ``geometry`` at 1/f of the
    resolution (module docstring): the PSF map from ``depth`` (m) where
    ``valid``, made on the coarse grid with ``coarse_patch``-px patches
    (``keep_range_m``: kept patches copied, as psf_map), the kernels
    area-resampled to the coarse pitch, ``patch_convolve`` (``pairs`` as
    there), and the result interpolated back. fallback_valid: blocks
    without ``valid`` pixels take the depth of these pixels instead (else
    they are copied, as patches without depth are). upsampling: 'cubic'
    (block means to point values, then Keys' cubic: rings a little below 0
    next to a hard-edged disc, left to the caller to clamp: the sum is kept)
    or 'linear' (bilinear of the block means). Returns (float32 (H, W,
    len(pairs)), the coarse PSFMap)."""
    h, w = image.shape[:2]
    img = block_mean(pad_to(np.asarray(image, np.float32), f), f)
    hc, wc = img.shape[:2]
    dc = coarse_depth(pad_to(depth, f), pad_to(valid, f), library.grid.far_m, f)
    if fallback_valid is not None:
        dc = np.where(np.isnan(dc), coarse_depth(pad_to(depth, f), pad_to(fallback_valid, f), library.grid.far_m,
                                                 f), dc)
    gc = coarse_geometry(geometry, f, hc, wc)
    pm = psf_map(library, gc, dc, coarse_patch, keep_range_m=keep_range_m, clamp_field=True)
    p = geometry.pixel_pitch_mm
    k = pm.kernels.shape[-1]
    kern = area_resample(pm.kernels, p, p * f, resampled_size(k, p, p * f))
    out = patch_convolve(img, kern, coarse_patch, ConvolveOptions(fft_backend=fft_backend), identity=pm.identity,
                         pairs=pairs)
    # block means of a blurred image brought back by Keys' cubic: closer to the
    # exact blur than bilinear on 6P's kernels (upsampling='linear' to compare)
    return upsample(out, f, h, w, upsampling, averages=upsampling == "cubic"), pm


def grouped_blur(x: np.ndarray, depth: np.ndarray, valid: np.ndarray, ident: np.ndarray, library, geometry,
                 options: MultiresOptions, *, pairs=None, keep_range_m=None, table=None):
    """``patch_convolve``'s blend sum_p t_p (x * K_p) over the m x m patches
    (m = ``options.patch``) of ``x`` (H, W, C), K_p the kernel psf_map gives
    patch p for the mean inverse depth (``depth`` metres) of its ``valid``
    pixels, with each patch at its level (:func:`patch_levels` with the
    options' rule): out = PC_0 + sum_{s >= 1} W_s (B_s - x), where
    PC_0 is ``patch_convolve`` with every patch not at level 0 copied
    (identity), W_s the tent blend of the indicator of the level-s patches
    (bilinear between patch centres, as patch_convolve's) and B_s ``x``
    blurred at 1/2^s (:func:`coarse_blur`) with the depths of the level-s
    patches (elsewhere in its box those of the rest). Each group is blurred
    on its box grown by the kernels' reach (``convolve.box_reach``). ident
    (nph, npw): patches copied as they are (no depth, kept sharp). pairs: as
    patch_convolve's (x's channel, kernel channel). A constant stays
    constant. table: the library's :func:`radius_table` (made here if None).
    Returns (float32 (H, W, len(pairs)), levels (nph, npw), -1 where ident)."""
    m, c, max_level = options.patch, options.c, options.max_level
    coarse_patch, fft_backend = options.coarse_patch, options.fft_backend
    grow = box_reach(library.kernel_size, m)
    h, w = depth.shape
    pr = np.array([(i, i) for i in range(x.shape[-1])] if pairs is None else pairs, int).reshape(-1, 2)
    table = radius_table(library) if table is None else table
    levels, _ = patch_levels(library, table, geometry, depth, valid, m, c, max_level)
    levels = np.where(ident, -1, levels)
    per_pixel = np.repeat(np.repeat(levels, m, 0), m, 1)[:h, :w]
    out = np.array(x[..., pr[:, 0]], np.float32, copy=True)
    if (levels == 0).any():
        # on the level-0 patches' box grown by the kernels' reach: beyond it
        # every window is a copy, and inside it no level-0 window reads the
        # box's reflected border
        ys, xs = patch_box(per_pixel == 0, m, grow)
        sub = geometry.crop(ys, xs)
        pm0 = psf_map(library, sub, np.where(valid[ys, xs] & (per_pixel[ys, xs] == 0), depth[ys, xs], np.nan), m,
                      keep_range_m=keep_range_m, crop=True)
        out[ys, xs] = patch_convolve(x[ys, xs], pm0.kernels, m, ConvolveOptions(fft_backend=fft_backend),
                                     identity=pm0.identity, pairs=pairs)
    for s in range(1, max_level + 1):
        group = levels == s
        if not group.any():
            continue
        ys, xs = patch_box(np.repeat(np.repeat(group, m, 0), m, 1)[:h, :w], m, grow)
        sub = geometry.crop(ys, xs)
        own = valid[ys, xs] & (per_pixel[ys, xs] == s)
        blurred = coarse_blur(x[ys, xs], depth[ys, xs], own, library, sub, 2 ** s, coarse_patch, pairs=pairs,
                              fallback_valid=valid[ys, xs], fft_backend=fft_backend)[0]
        wgt = upsample(group[ys.start // m:-(-ys.stop // m), xs.start // m:-(-xs.stop // m), None]
                       .astype(np.float32), m, ys.stop - ys.start, xs.stop - xs.start)
        out[ys, xs] += wgt * (blurred - x[ys, xs][..., pr[:, 0]])
    return out, levels


def plain_blur(img: np.ndarray, depth: np.ndarray, library, geometry, options: MultiresOptions, *,
               keep_range_m=None):
    """The plain patch-wise bokeh (``BokehOptions(occlusion=False)``) of
    ``img`` (H, W, 3) with ``depth`` (H, W) metres, each patch at its level
    (:func:`grouped_blur`); patches without valid depth or whose depth is in
    ``keep_range_m`` (near, far metres) are copied, as the exact path's.
    Returns (image float32 (H, W, 3), info dict)."""
    from .psfmap import patch_inverse_depth
    from ..psf.library import valid_depth_mask

    m = options.patch
    valid = valid_depth_mask(depth)
    inv, has = patch_inverse_depth(depth, m, library.grid.far_m)
    d_patch = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    ident = ~has
    if keep_range_m is not None:
        ident |= has & (d_patch >= keep_range_m[0]) & (d_patch <= keep_range_m[1])
    if valid.any():
        library.ensure(bins=library.bins_needed(depth[valid], clamp_near=True))
    out, levels = grouped_blur(img, depth, valid, ident, library, geometry, options, keep_range_m=keep_range_m)
    info = {"multires_patches_per_level": [int((levels == s).sum()) for s in range(options.max_level + 1)]}
    # light is never negative: the cubic's undershoot next to a hard-edged disc
    # (all at level 0: left as the exact path's, bit for bit)
    return (np.maximum(out, 0.0) if (levels > 0).any() else out), info
