"""Depth-aware aberration simulation and lens bokeh on an all-in-focus RGB-D image.

simulate(): the paper's training-data degradation: every m x m patch blurred
with the lens's PSF for its field, azimuth and depth (depth-aware), or with
one depth for the whole image (``fixed_depth_m``: the paper's depth-unaware
baseline); then the lens's geometric distortion applied to both the sharp and
the aberrated image (so they stay pixel-aligned, the paper's choice) and,
optionally, sensor noise.

bokeh(): the depth of field of a target lens on a sharp image. What is kept
sharp is a depth range [near, far] (the paper's mask: identity PSF inside
it) or a focus distance (the library refocused there). Two renderers:
``occlusion=False`` is the plain patch-wise blur; ``occlusion=True`` (the
default) splits the scene into depth layers and composites them back to
front, each blurred with its own PSFs and carrying its blurred coverage, so
a sharp subject does not bleed into a blurred background nor get a halo.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from ..optics.errors import InputRangeError
from ..psf.compute import KernelTooSmallWarning, PSFSettings
from ..psf.library import LibraryGrid, PSFLibrary
from .convolve import patch_convolve
from .geometry import ImageGeometry
from .psfmap import PSFMap, psf_map, valid_depth_mask


class Cancelled(Exception):
    """Raised by :func:`bokeh` when its ``cancelled()`` callback returns True."""


@dataclass
class RenderResult:
    image: np.ndarray                 # (H, W, 3) float32, linear
    info: dict = field(default_factory=dict)
    sharp: np.ndarray | None = None   # simulate(): the sharp image, distorted alike
    psf_map: PSFMap | None = None


def _check(image, depth):
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("image shape", img.shape, "(H, W, 3)")
    if not np.isfinite(img).all():
        raise InputRangeError("image", "non-finite values", "finite linear RGB")
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != img.shape[:2]:
        raise InputRangeError("depth map shape", d.shape, f"{img.shape[:2]}, the image's")
    return img, d


MAX_FITTED_KERNEL = 129      # px: beyond this a patch-wise FFT blur costs more than it is worth here


def open_library(lens, geometry: ImageGeometry, settings: PSFSettings | None = None,
                 grid: LibraryGrid | None = None, *, cache: bool = True, fit_depth_m=None,
                 progress=None) -> PSFLibrary:
    """The lens's PSF library sampled at the image's pixel pitch.

    fit_depth_m: a depth map (metres) whose depth bins are computed now; if
    their PSFs spill out of the settings' kernel (less than 99 % of the rays
    inside, as a fast lens's defocus blur at full resolution does), the
    library is reopened with the odd kernel size that holds them, at most
    MAX_FITTED_KERNEL px (beyond that the usual KernelTooSmallWarning says
    how much is clipped). Without it the kernel size is the settings'.
    progress(done, total): called as PSF bins are computed."""
    s = replace(settings or PSFSettings(), pixel_pitch_mm=geometry.pixel_pitch_mm)
    library = PSFLibrary.open(lens, s, grid, cache=cache)
    if fit_depth_m is None:
        return library
    d = np.asarray(fit_depth_m, dtype=np.float64)
    d = d[valid_depth_mask(d)]
    if d.size == 0:
        return library
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)       # answered below by a larger kernel
        library.ensure(d, clamp_near=True, progress=progress)
    need = int(library.kernel_size_needed[library.computed].max())
    if need <= library.kernel_size or library.kernel_size >= MAX_FITTED_KERNEL:
        return library
    library = PSFLibrary.open(lens, replace(s, kernel_size=min(need | 1, MAX_FITTED_KERNEL)), grid, cache=cache)
    library.ensure(d, clamp_near=True, progress=progress)
    return library


def simulate(image, depth, lens, *, geometry: ImageGeometry | None = None, patch: int = 16,
             library: PSFLibrary | None = None, fixed_depth_m: float | None = None,
             distortion: bool = True, noise: dict | None = None, seed: int | None = None) -> RenderResult:
    """Aberrated image of an all-in-focus ``image`` (H, W, 3) with metric
    ``depth`` (H, W) through ``lens``. noise: keyword arguments of
    ``noise.add_sensor_noise`` (needs ``seed``)."""
    img, d = _check(image, depth)
    geometry = geometry or ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1])
    library = library or open_library(lens, geometry, fit_depth_m=d)
    pm = psf_map(library, geometry, d, patch, fixed_depth_m=fixed_depth_m)
    out = patch_convolve(img, pm.kernels, patch, identity=pm.identity)
    sharp = img
    info = dict(pm.info, depth_aware=fixed_depth_m is None)
    if distortion:
        from .distortion import distort, radial_distortion
        # one warp for both images: the sample coordinates are computed once
        both = distort(np.concatenate([out, img], axis=-1), lens, geometry, distortion=radial_distortion(lens))
        out, sharp = both[..., :3], both[..., 3:]
    if noise is not None:
        if seed is None:
            raise InputRangeError("seed", None, "an integer: noise needs an explicit seed")
        from .noise import add_sensor_noise
        out = add_sensor_noise(out, seed=seed, **noise)
        info["noise"] = dict(noise, seed=seed)
    return RenderResult(out.astype(np.float32), info, sharp.astype(np.float32), pm)


def _layers(inv: np.ndarray, valid: np.ndarray, n_layers: int):
    """Split valid pixels into depth layers of equal width in diopters,
    ordered far to near: list of boolean masks."""
    lo, hi = float(inv[valid].min()), float(inv[valid].max())
    if hi - lo < 1e-12:
        return [valid]
    edges = np.linspace(lo, hi, n_layers + 1)
    idx = np.clip(np.searchsorted(edges, inv, side="right") - 1, 0, n_layers - 1)
    return [valid & (idx == i) for i in range(n_layers) if (valid & (idx == i)).any()]


def _box(mask: np.ndarray, m: int, grow: int) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s bounding box grown by ``grow`` px and
    aligned to the m-px patch grid (so its patches are the image's)."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    y0, x0 = max(0, (rows[0] - grow) // m * m), max(0, (cols[0] - grow) // m * m)
    y1, x1 = min(h, -(-(rows[-1] + 1 + grow) // m) * m), min(w, -(-(cols[-1] + 1 + grow) // m) * m)
    return slice(int(y0), int(y1)), slice(int(x0), int(x1))


def bokeh(image, depth, lens, *, keep: tuple[float, float] | None = None, focus_m: float | None = None,
          geometry: ImageGeometry | None = None, patch: int = 16, occlusion: bool = True,
          n_layers: int = 12, library: PSFLibrary | None = None, settings: PSFSettings | None = None,
          cancelled=None) -> RenderResult:
    """``image`` as ``lens`` would take it, keeping [near, far] metres sharp
    (``keep``) or focused at ``focus_m`` metres. Invalid depths (NaN, 0,
    negative) are left sharp. ``cancelled()``, if given, is called before each
    layer's convolution; when it returns True, :class:`Cancelled` is raised."""
    if (keep is None) == (focus_m is None):
        raise InputRangeError("keep / focus", (keep, focus_m), "exactly one of a keep range or a focus distance")
    if keep is not None and not (0 < keep[0] <= keep[1]):
        raise InputRangeError("keep", keep, "0 < near <= far metres")
    img, d = _check(image, depth)
    geometry = geometry or ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1])
    if library is None:
        s = settings or PSFSettings()
        if focus_m is not None:
            s = replace(s, focus_distance_m=focus_m)
        library = open_library(lens, geometry, s, fit_depth_m=d)
    valid = valid_depth_mask(d)
    far = library.grid.far_m
    inv = np.where(valid & (d < far), 1.0 / np.where(valid, d, 1.0), 0.0)
    kept = np.zeros(d.shape, bool) if keep is None else valid & (d >= keep[0]) & (d <= keep[1])
    info = {"occlusion": occlusion, "kept_pixels": int(kept.sum()), "invalid_depth_pixels": int((~valid).sum())}
    if not occlusion:
        if cancelled is not None and cancelled():
            raise Cancelled("bokeh cancelled")
        pm = psf_map(library, geometry, d, patch, keep_range_m=keep)
        out = patch_convolve(img, pm.kernels, patch, identity=pm.identity)
        return RenderResult(out, dict(info, **pm.info), psf_map=pm)
    # layered, back to front: each layer's colour and coverage blurred alike.
    # ``col`` is the colour seen so far, un-premultiplied, where ``seen``: what
    # lies behind a layer where nothing farther was seen (hidden by a nearer
    # layer, or the farthest layer's own holes) takes the colour spread from
    # around it (normalised blur) instead of black: no dark seam where a
    # continuous surface crosses from one layer to the next, no dark halo.
    col = np.zeros_like(img)
    seen = np.zeros(img.shape[:2] + (1,), bool)
    sharp_mask = kept | ~valid
    layers = _layers(inv, valid & ~kept, n_layers) if (valid & ~kept).any() else []
    # the kept (sharp) pixels form their own layer at their depth, composited in order
    order = [(float(inv[m_].mean()), m_, False) for m_ in layers]
    if sharp_mask.any():
        order += [(float(inv[kept].mean()) if kept.any() else -1.0, sharp_mask, True)]
    order.sort(key=lambda t: t[0])                        # far (small diopters) first
    # each layer is blurred on its own patch-aligned bounding box, grown by the
    # kernel's reach: outside it the layer is empty and its blur is zero
    grow = patch * math.ceil((library.kernel_size // 2 + patch) / patch)
    for mask, is_sharp in ((m_, s_) for _, m_, s_ in order):
        if cancelled is not None and not is_sharp and cancelled():
            raise Cancelled("bokeh cancelled")
        ys, xs = _box(mask, patch, grow if not is_sharp else 0)
        a = mask[ys, xs][..., None]
        if is_sharp:
            col[ys, xs] = np.where(a, img[ys, xs], col[ys, xs])
            seen[ys, xs] |= a
            continue
        sub = replace(geometry, height=ys.stop - ys.start, width=xs.stop - xs.start,
                      center_px=(geometry.center_px[0] - ys.start, geometry.center_px[1] - xs.start))
        pm = psf_map(library, sub, np.where(mask[ys, xs], d[ys, xs], np.nan), patch)
        af = a.astype(np.float32)
        # each colour's coverage blurred with that colour's own PSF: the
        # normalisation above is then exact for any colour fringe
        blurred = patch_convolve(np.concatenate([img[ys, xs] * af, af], axis=-1), pm.kernels, patch,
                                 identity=pm.identity, pairs=((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2)))
        cover = np.clip(blurred[..., 3:], 0.0, 1.0)
        behind = seen[ys, xs]
        premultiplied = blurred[..., :3] + (1.0 - cover) * np.where(behind, col[ys, xs], 0.0)
        total = np.where(behind, 1.0, cover)
        seen[ys, xs] = (total > 1e-4).all(axis=-1, keepdims=True)
        col[ys, xs] = np.where(total > 1e-4, premultiplied / np.maximum(total, 1e-4), 0.0)
    info["layers"] = len(order)
    return RenderResult(col, info)
