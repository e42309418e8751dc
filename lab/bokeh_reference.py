"""Per-pixel references of a lens's depth of field: every pixel its own PSF.

``scatter_reference``: each source pixel x spreads its light with the PSF of
its own field, azimuth and depth, out(y) = sum_x K_x(y - x) I(x). It is what
the lens forms from a scene without occlusion: a point's light lands where
its own PSF says, whatever lies beside it. (The gather form,
``accuracy.per_pixel_reference``, gives each output pixel the PSF of its own
depth instead: right for a smooth depth map, wrong at a depth edge, where a
sharp pixel beside a blurred background would receive none of it.) What no
per-pixel image model holds is occlusion within the aperture (a foreground
edge hiding part of a background point's cone); the occlusion-aware
renderer approximates that, so at such edges neither is ground truth.

``per_pixel_references``: both forms from the same kernels.
``crop_reference``: the same for a crop of a larger image, from the crop
grown by the kernel's reach (every source whose light reaches the crop), so
a crop of the reference equals the same crop of a full-frame one.

Depth conventions (docs/design.md): beyond the library's far limit, inf and
Blender's background use the infinity PSF; nearer than its near limit is
clamped to it; invalid depths (NaN, 0, negative) are left sharp.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from dcdi_core.errors import InputRangeError
from dcdi_core.render.psfmap import pixel_kernels
from dcdi_core.psf.library import valid_depth_mask


def scatter_reference(img, depth, library, geometry, *, rows_per_block: int | None = None) -> np.ndarray:
    """out(y) = sum_x K_x(y - x) I(x) over the image's own pixels (light
    spread past its border is lost, none comes in from beyond it): (H, W, 3)
    float32."""
    return _references(img, depth, library, geometry, rows_per_block, gather=False)[0]


def per_pixel_references(img, depth, library, geometry, *, rows_per_block: int | None = None):
    """(scatter, gather): ``scatter_reference`` and the gather form from the
    same kernels, out(y) = sum_t K_y(t) I(y - t) with zeros beyond the
    border (``accuracy.per_pixel_reference`` reflects it instead)."""
    return _references(img, depth, library, geometry, rows_per_block, gather=True)


def _references(img, depth, library, geometry, rows_per_block, gather: bool):
    """Vectorised over blocks of rows: each block's kernels computed once,
    weighted by its pixels and added into the output once per kernel tap
    (scatter); and, if ``gather``, applied to each pixel's neighbourhood."""
    img = np.asarray(img, np.float32)
    h, w, _ = img.shape
    if img.shape != (geometry.height, geometry.width, 3):
        raise InputRangeError("image shape", img.shape, f"({geometry.height}, {geometry.width}, 3), the geometry's")
    d = np.asarray(depth, np.float64)
    if d.shape != (h, w):
        raise InputRangeError("depth map shape", d.shape, f"{(h, w)}, the image's")
    k = library.kernel_size
    r = k // 2
    if rows_per_block is None:                 # about 64 MB of weighted kernels per block
        rows_per_block = max(1, int(64e6 // (w * 3 * k * k * 4)))
    out = np.zeros((h + 2 * r, w + 2 * r, 3), np.float32)
    pad = np.pad(img, ((r, r), (r, r), (0, 0))) if gather else None
    out_g = np.zeros((h, w, 3), np.float32) if gather else None
    for y0 in range(0, h, rows_per_block):
        y1 = min(h, y0 + rows_per_block)
        rr, cc = np.mgrid[y0:y1, 0:w]
        kern = pixel_kernels(library, geometry, rr.ravel(), cc.ravel(), d[y0:y1].ravel())
        # taps first, contiguous: (k, k, rows, w, 3)
        kt = np.ascontiguousarray(kern.reshape(y1 - y0, w, 3, k, k).transpose(3, 4, 0, 1, 2))
        wk = kt * img[y0:y1]
        for ty in range(k):
            for tx in range(k):
                # source (y, x) with tap t lands on y + t - r: padded row y + ty
                out[y0 + ty:y1 + ty, tx:tx + w] += wk[ty, tx]
                if gather:      # output y reads I(y - (t - r)): padded row y + 2r - ty
                    out_g[y0:y1] += kt[ty, tx] * pad[y0 + 2 * r - ty:y1 + 2 * r - ty, 2 * r - tx:2 * r - tx + w]
    return out[r:r + h, r:r + w], out_g


def crop_reference(img, depth, library, geometry, box: tuple[int, int, int, int], *, gather: bool = False):
    """``scatter_reference`` of the full image, on its crop ``box`` = (row0,
    row1, col0, col1) only: computed from the crop grown by the kernel's
    radius (clipped at the image's border, where no light comes from
    beyond the image). gather: return (scatter, gather) crops
    (``per_pixel_references``; the gather's input is the grown crop, so
    it too equals the full frame's away from the image's border)."""
    y0, y1, x0, x1 = box
    h, w = np.asarray(depth).shape
    if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
        raise InputRangeError("crop box", box, f"0 <= row0 < row1 <= {h}, 0 <= col0 < col1 <= {w}")
    r = library.kernel_size // 2
    gy0, gy1, gx0, gx1 = max(0, y0 - r), min(h, y1 + r), max(0, x0 - r), min(w, x1 + r)
    sub = replace(geometry, height=gy1 - gy0, width=gx1 - gx0,
                  center_px=(geometry.center_px[0] - gy0, geometry.center_px[1] - gx0))
    refs = _references(np.asarray(img)[gy0:gy1, gx0:gx1], np.asarray(depth)[gy0:gy1, gx0:gx1], library, sub,
                       None, gather)
    inner = (slice(y0 - gy0, y1 - gy0), slice(x0 - gx0, x1 - gx0))
    return (refs[0][inner], refs[1][inner]) if gather else refs[0][inner]
