"""The PSF map of an image: one RGB kernel per m x m patch, for its field, azimuth and depth.

Depth per patch: the paper averages the patch's depths (AvgPool); we average
*inverse* depth over the patch's valid pixels, because blur scales with
diopters and infinity (0 diopters) then needs no special case. Depth
conventions (docs/design.md): NaN, 0 and negative depths are invalid and left out
of the average; >= the library's far limit, inf and Blender's 1e10 count as
infinity. A patch with no valid depth keeps the identity kernel (it is left
sharp) and is counted in the map's ``info``.

The library is radial (fields along sensor +y, kernel rows along the radial
direction); each patch's kernel is rotated so that its radial axis points
from the optical axis to the patch centre (bilinear resampling, renormalised).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputRangeError
from ..psf.library import valid_depth_mask
from .convolve import rings_needed


def patch_inverse_depth(depth: np.ndarray, m: int, far_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean inverse depth (1/m) of each m x m patch's valid pixels, and a mask
    of patches that have any. Depths >= far_m count as 0 diopters."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise InputRangeError("depth map shape", d.shape, "(H, W)")
    h, w = d.shape
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    valid = valid_depth_mask(d)
    inv = np.where(valid & (d < far_m), 1.0 / np.where(valid, d, 1.0), 0.0)
    pad = ((0, nph * m - h), (0, npw * m - w))
    inv = np.pad(inv, pad).reshape(nph, m, npw, m).sum(axis=(1, 3))
    cnt = np.pad(valid.astype(np.float64), pad).reshape(nph, m, npw, m).sum(axis=(1, 3))
    has = cnt > 0
    return np.where(has, inv / np.maximum(cnt, 1), 0.0), has


def _rotate_flat(src: np.ndarray, outward: np.ndarray, k: int, target_sum: np.ndarray,
                 keep_peak: bool = True) -> np.ndarray:
    """Bilinear rotation of flat kernels src (n, C, k*k) whose rows run along
    the radial direction to ``outward`` (n, 2) unit (row, col); zero outside;
    each channel scaled to ``target_sum`` (n, C). keep_peak: the centre's
    excess over its neighbours is not interpolated (below)."""
    r = k // 2
    dr, dc = np.meshgrid(np.arange(k, dtype=np.float32) - r, np.arange(k, dtype=np.float32) - r, indexing="ij")
    dr, dc = dr.ravel(), dc.ravel()
    ur = outward[:, 0, None].astype(np.float32)
    uc = outward[:, 1, None].astype(np.float32)
    a = dr * ur + dc * uc + r            # along the radial axis -> source row
    b = -dr * uc + dc * ur + r           # tangential -> source column (kernels mirror in it)
    r0, c0 = np.floor(a), np.floor(b)
    fr, fc = a - r0, b - c0
    r0, c0 = r0.astype(np.int64), c0.astype(np.int64)
    acc = np.zeros(src.shape, np.float32)
    n, c, kk = src.shape
    # A pixel histogram does not say where in the centre pixel its rays
    # fell: an in-focus spot smaller than a pixel is one peaked centre
    # value, which a rotation about the centre leaves in place, but which
    # interpolation would spread over the neighbours (a delta rotated by 45
    # degrees bilinearly keeps only 74 %). So the centre's excess over its
    # largest neighbour stays a point at the centre, and only the smooth
    # rest is interpolated (nearly all of a smooth kernel: bilinear as
    # before). Measured against rotated rays in report simulation-accuracy.
    centre = r * k + r
    src = np.array(src, dtype=np.float32, copy=True)
    peak = src[:, :, centre] if keep_peak else np.zeros_like(src[:, :, centre])
    if keep_peak and k >= 3:
        ring = [centre + dy * k + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
        peak = np.maximum(peak - src[:, :, ring].max(axis=-1), 0.0)
    acc[:, :, centre] = peak
    src[:, :, centre] -= peak
    # one flat gather per tap (1.7x faster than take_along_axis, measured)
    flat = np.ascontiguousarray(src).ravel()
    base = (np.arange(n) * c * kk)[:, None, None] + (np.arange(c) * kk)[None, :, None]
    for oy, ox, wgt in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                        (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr, cc = r0 + oy, c0 + ox
        ok = (rr >= 0) & (rr < k) & (cc >= 0) & (cc < k)
        idx = np.where(ok, rr * k + cc, 0)[:, None, :]
        acc += np.take(flat, base + idx) * (wgt * ok)[:, None, :]
    after = acc.sum(axis=-1, keepdims=True)
    acc *= np.where(after > 0, target_sum[..., None] / np.where(after > 0, after, 1.0), 0.0).astype(np.float32)
    return acc


def _rotate_flat_fast(src: np.ndarray, outward: np.ndarray, k: int, target_sum: np.ndarray) -> np.ndarray:
    """``_rotate_flat`` (keep_peak), the same maths laid out for speed: the
    source is zero-padded (1 px before, 2 after) and its out-of-range
    coordinates clipped onto the padding, so the four taps need no masks and
    are one flat index each (the first plus a constant offset).
    Equal to ``_rotate_flat`` to float32 rounding (tested)."""
    r = k // 2
    n, c, kk = src.shape
    p = k + 3
    dr, dc = np.meshgrid(np.arange(k, dtype=np.float32) - r, np.arange(k, dtype=np.float32) - r, indexing="ij")
    dr, dc = dr.ravel(), dc.ravel()
    ur = outward[:, 0, None].astype(np.float32)
    uc = outward[:, 1, None].astype(np.float32)
    # rows of the padded source: -1 .. k + 1; a coordinate beyond reads only zeros there
    a = np.clip(dr * ur + dc * uc + r, -1.0, float(k))
    b = np.clip(-dr * uc + dc * ur + r, -1.0, float(k))
    r0, c0 = np.floor(a), np.floor(b)
    fr, fc = a - r0, b - c0
    idx = ((r0 + 1) * p + (c0 + 1)).astype(np.intp)                        # (n, kk)
    pad = np.zeros((n, c, p, p), np.float32)
    pad[:, :, 1:k + 1, 1:k + 1] = src.reshape(n, c, k, k)
    centre = r * k + r
    peak = src[:, :, centre].astype(np.float32)
    if k >= 3:
        ring = [centre + dy * k + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
        peak = np.maximum(peak - src[:, :, ring].max(axis=-1), 0.0)
    pad[:, :, r + 1, r + 1] -= peak
    flat = pad.ravel()
    full = (np.arange(n * c, dtype=np.intp) * (p * p)).reshape(n, c, 1) + idx[:, None, :]
    gr, gc = 1.0 - fr, 1.0 - fc
    acc = np.take(flat, full) * (gr * gc)[:, None, :]
    tmp = np.empty_like(acc)
    for off, wgt in ((1, gr * fc), (p, fr * gc), (p + 1, fr * fc)):
        np.take(flat[off:], full, out=tmp)
        tmp *= wgt[:, None, :]
        acc += tmp
    acc[:, :, centre] += peak
    after = acc.sum(axis=-1, keepdims=True)
    acc *= np.where(after > 0, target_sum[..., None] / np.where(after > 0, after, 1.0), 0.0).astype(np.float32)
    return acc


def rotate_radial_kernels(kernels: np.ndarray, outward: np.ndarray, chunk: int = 256,
                          keep_peak: bool = True) -> np.ndarray:
    """Rotate kernels (P, C, k, k) whose rows run along the radial direction so
    that it points along ``outward`` (P, 2) = unit (row, col) vectors.
    Bilinear (the centre's peak kept in place unless ``keep_peak`` is
    False), zero outside, each channel renormalised to its former sum.
    Chunks run on the thread pool (float32 throughout)."""
    from ..parallel import thread_pool

    p, c, k, _ = kernels.shape
    flat = np.ascontiguousarray(kernels, dtype=np.float32).reshape(p, c, k * k)
    out = np.empty((p, c, k * k), np.float32)

    def work(sl):
        out[sl] = _rotate_flat(flat[sl], outward[sl], k, flat[sl].sum(axis=-1), keep_peak)

    list(thread_pool().map(work, [slice(i, min(i + chunk, p)) for i in range(0, p, chunk)]))
    return out.reshape(p, c, k, k)


def outward_directions(geometry, rows, cols) -> np.ndarray:
    """Unit (row, col) vectors (n, 2) from the optical axis to pixels (rows,
    cols) of ``geometry``; (1, 0) on the axis."""
    vec = np.stack([np.asarray(rows, np.float64) - geometry.center_px[0],
                    np.asarray(cols, np.float64) - geometry.center_px[1]], -1)
    norm = np.hypot(vec[:, 0], vec[:, 1])
    return np.where(norm[:, None] > 1e-9, vec / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])


def pixel_kernels(library, geometry, rows, cols, depth) -> np.ndarray:
    """The PSFs (n, 3, k, k) of pixels (rows, cols) of ``geometry`` at depths
    ``depth`` (metres, n): the library's, at the pixel's field, rotated to
    its azimuth (every pixel of the kernel, the library's size); a unit
    impulse for invalid depths. The per-pixel references' kernels
    (``point_kernels``: the same, as the PSF map computes them)."""
    rows, cols = np.asarray(rows), np.asarray(cols)
    d = np.asarray(depth, np.float64)
    valid = valid_depth_mask(d)
    d = np.where(~valid, library.grid.far_m, d)
    d = np.where(d >= library.grid.far_m, np.inf, np.maximum(d, library.grid.near_m))
    field = np.minimum(geometry.field(rows, cols), 1.0)
    kern = rotate_radial_kernels(library.at(field, d), outward_directions(geometry, rows, cols))
    if not valid.all():
        r = library.kernel_size // 2
        kern[~valid] = 0.0
        kern[~valid, :, r, r] = 1.0
    return kern


def point_kernels(library, geometry, rows, cols, depth, support_eps: float = 1e-3) -> np.ndarray:
    """The kernels (n, 3, k', k') ``psf_map`` gives patches centred at (rows,
    cols) of ``geometry`` with depths ``depth`` (metres > 0, inf; clamped to
    the library's near limit): each over the square its energy needs (all
    but ``support_eps``), k' the largest such square (<= the library's k)."""
    d = np.maximum(np.asarray(depth, np.float64), library.grid.near_m)
    field = np.minimum(geometry.field(rows, cols), 1.0)
    plan = kernel_plan(library, field, d, support_eps)
    k = 2 * int(plan[3].max()) + 1
    out = np.zeros((len(d), 3, k, k), np.float32)
    from ..parallel import one_blas_thread
    with one_blas_thread():
        _rotated_patch_kernels(plan, outward_directions(geometry, rows, cols), out, np.arange(len(d)))
    return out


def support_radius(psf: np.ndarray, eps: float) -> np.ndarray:
    """Radius rho (px, integer) of the disk about the kernel centre that holds
    all but ``eps`` of every channel's energy: psf (..., C, k, k) -> (...).
    The disk is what survives any rotation, so a kernel cropped to half-width
    rho + 1 (bilinear spread) and rotated loses at most eps."""
    r = psf.shape[-1] // 2
    d = np.arange(-r, r + 1)
    return rings_needed(psf, np.ceil(np.hypot(d[:, None], d[None, :]) - 1e-9), eps)


def kernel_plan(library, field, depth, eps):
    """What each patch's kernel is made of: (entry (n, 4) library entries
    (bin x field), weight (n, 4) float32 linear in field and inverse depth,
    target (n, C) the interpolated kernel's channel sums, half (n,) the
    half-width of the square its energy needs (support_radius + 1), psf
    (entries, C, k, k) the library's kernels)."""
    i0, i1, t = library.depth_bins(depth, clamp_near=True)
    library.ensure(bins=library.bins_needed(depth, clamp_near=True))
    j0, j1, u = library.field_weights(field)
    nf = len(library.fields)
    k = library.kernel_size
    r = k // 2
    psf = library.psf.reshape(-1, 3, k, k)                               # (bins x fields, C, k, k)
    entry = np.stack([i0 * nf + j0, i0 * nf + j1, i1 * nf + j0, i1 * nf + j1], -1)
    weight = np.stack([(1 - t) * (1 - u), (1 - t) * u, t * (1 - u), t * u], -1).astype(np.float32)
    used = np.unique(entry[weight > 0])
    rho = np.zeros(len(psf), np.int64)
    rho[used] = support_radius(psf[used], eps)
    full_sum = psf[used].sum(axis=(-2, -1))                              # (used entries, C)
    sums = np.zeros((len(psf), 3), full_sum.dtype)
    sums[used] = full_sum
    half = np.minimum(r, np.where(weight > 0, rho[entry], 0).max(axis=-1) + 1)
    target = np.einsum("nq,nqc->nc", weight, sums[entry])                # the interpolated kernel's sums
    return entry, weight, target, half, psf


def _rotated_patch_kernels(plan, outward, kernels_flat, where, chunk=256, fast=True):
    """Write into kernels_flat[where] (n, C, k, k) the kernels of ``plan``
    (``kernel_plan`` at the patches' field and depth (n,)): the library's
    kernels interpolated linearly in field and inverse depth and rotated to
    ``outward``, each computed only over the centred square its energy needs
    (support_radius + 1): the cost of a small PSF is that of its support,
    not of the library's kernel size; k may be smaller than the library's
    (at least the largest square). fast: the rotation by
    ``_rotate_flat_fast`` (equal to float32 rounding), else ``_rotate_flat``.
    Returns the half-widths (n,) of the squares computed."""
    from ..parallel import thread_pool

    entry, weight, target, half, psf = plan
    r = psf.shape[-1] // 2
    ro = kernels_flat.shape[-1] // 2

    def work(sel, h):
        crop = psf[:, :, r - h:r + h + 1, r - h:r + h + 1]
        kc = 2 * h + 1
        g = crop[entry[sel]].reshape(len(sel), 4, 3 * kc * kc)          # (n, 4, C kc^2)
        # a weighted sum, not matmul: a BLAS call here would start its own
        # threads inside the pool's (measured: 3x the time, mostly spinning)
        blend = np.einsum("nq,nqx->nx", weight[sel], g).reshape(len(sel), 3, kc * kc)
        rot = (_rotate_flat_fast if fast else _rotate_flat)(blend, outward[sel], kc, target[sel])
        kernels_flat[where[sel], :, ro - h:ro + h + 1, ro - h:ro + h + 1] = rot.reshape(len(sel), 3, kc, kc)

    jobs = []
    for h in np.unique(half):
        sel = np.nonzero(half == h)[0]
        jobs += [(sel[s:s + chunk], int(h)) for s in range(0, len(sel), chunk)]
    list(thread_pool().map(lambda job: work(*job), jobs))
    return half


@dataclass
class PSFMap:
    """Kernels (nph, npw, 3, k, k) for an image, with what was done to get them."""

    kernels: np.ndarray
    identity: np.ndarray          # (nph, npw) patches left sharp (no valid depth, or kept in focus)
    patch: int
    depth_m: np.ndarray           # (nph, npw) the depth each kernel is for (inf; nan where identity)
    field: np.ndarray             # (nph, npw) normalised field of the patch centres
    info: dict
    support_px: np.ndarray | None = None   # (nph, npw) half-width outside which each kernel is zero


def identity_kernel(k: int) -> np.ndarray:
    e = np.zeros((3, k, k), np.float32)
    e[:, k // 2, k // 2] = 1.0
    return e


def psf_map(library, geometry, depth: np.ndarray, m: int = 16, *, fixed_depth_m: float | None = None,
            keep_range_m: tuple[float, float] | None = None, clamp_near: bool = True,
            support_eps: float = 1e-3, clamp_field: bool = False, method: str = "fast",
            accelerator: str | None = None, crop: bool = False) -> PSFMap:
    """Kernels for every m x m patch of an image of ``geometry`` with ``depth``.

    fixed_depth_m: one depth for every patch (the paper's depth-unaware
    baseline). keep_range_m: patches whose depth lies in [near, far] get the
    identity (kept sharp). Depths below the library's near limit are clamped
    to it when ``clamp_near`` (the count is in ``info``), else an error.
    support_eps: each kernel is computed over the disk that holds all but
    this fraction of its energy (and rescaled to its full sum); 0 keeps every
    nonzero pixel (see ``support_radius``). clamp_field: patches beyond the
    sensor's corner (field > 1) get the corner's PSFs instead of an error
    (for a margin that only feeds the frame's border). method: 'fast' (the
    rotation laid out for speed) or 'exact' (the former layout; both give
    the same kernels to float32 rounding, tested). accelerator: None
    (numpy) or 'torch' (``accel_torch.py``: the same kernels in torch).
    crop: the kernels' size is the largest square any patch's energy needs
    (2 max(support) + 1, at least 1) instead of the library's: the same
    kernels' centres, less memory and convolution where the blur is small."""
    if method not in ("fast", "exact"):
        raise InputRangeError("psf_map method", method, "'fast' or 'exact'")
    if accelerator not in (None, "torch"):
        raise InputRangeError("accelerator", accelerator, "None (numpy) or 'torch'")
    if accelerator == "torch":
        from . import accel_torch
        if not accel_torch.available():
            raise InputRangeError("accelerator", accelerator, "None here: torch cannot be imported")
    if m < 1:
        raise InputRangeError("patch", m, ">= 1 pixel")
    h, w = geometry.height, geometry.width
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (h, w):
        raise InputRangeError("depth map shape", depth.shape, f"({h}, {w}), the image's")
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    far = library.grid.far_m
    near = library.grid.near_m
    if fixed_depth_m is not None:
        inv = np.full((nph, npw), 0.0 if fixed_depth_m >= far else 1.0 / fixed_depth_m)
        has = np.ones((nph, npw), bool)
    else:
        inv, has = patch_inverse_depth(depth, m, far)
    d = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    clamped = int(((d < near) & has).sum())
    if clamped and not clamp_near:
        raise InputRangeError("depth", float(d[has].min()), f">= the library's near limit {near} m")
    d = np.where(has, np.maximum(d, near), np.nan)
    # patch centres on the sensor
    rows = np.minimum(np.arange(nph) * m + (m - 1) / 2.0, h - 1)
    cols = np.minimum(np.arange(npw) * m + (m - 1) / 2.0, w - 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    field = geometry.field(rr, cc)
    if not clamp_field and (field > 1.0 + 1e-9).any():
        raise InputRangeError("image field", float(field.max()),
                              "<= 1: the image must lie within the sensor (check its pixel pitch)")
    field = np.minimum(field, 1.0)
    keep = np.zeros((nph, npw), bool)
    if keep_range_m is not None:
        lo, hi = keep_range_m
        keep = has & (d >= lo) & (d <= hi)
    ident = ~has | keep
    todo = ~ident
    k = library.kernel_size
    plan = None
    if todo.any():
        plan = kernel_plan(library, field[todo], np.where(np.isfinite(d[todo]), d[todo], np.inf), support_eps)
        if crop:
            k = 2 * int(plan[3].max()) + 1
    elif crop:
        k = 1
    kernels = np.zeros((nph, npw, 3, k, k), np.float32)
    kernels[ident] = identity_kernel(k)
    support = np.zeros((nph, npw), np.int64)
    if plan is not None:
        from ..parallel import one_blas_thread
        args = (plan, outward_directions(geometry, rr[todo], cc[todo]), kernels.reshape(nph * npw, 3, k, k), np.flatnonzero(todo))
        if accelerator == "torch":
            from .accel_torch import rotated_patch_kernels
            support[todo] = rotated_patch_kernels(*args)
        else:
            with one_blas_thread():
                support[todo] = _rotated_patch_kernels(*args, fast=method == "fast")
    info = {"patches": int(nph * npw), "no_valid_depth": int((~has).sum()), "kept_sharp": int(keep.sum()),
            "clamped_to_near_limit": clamped, "depth_bins_computed": int(library.computed.sum())}
    return PSFMap(kernels, ident, m, np.where(has, d, np.nan), field, info, support)
