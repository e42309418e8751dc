"""The patch size of a depth layer: as large as its kernels' interpolation allows.

The patch-wise blur (``convolve.patch_convolve``) gives an output pixel x
the kernel sum_p t_p(x) K_p: the kernels of the patches whose windows cover
it, weighted by the blend ramps t_p. Its cost is the FFT of each window's
input, (m + 2b + 2h)^2 points for m^2 output pixels (m the patch, b the
blend's half-width, h the kernel's half-width): at a 63-px kernel, 36
points per pixel with 16-px patches and the tent (b = 8), 5 with 64-px
patches and 8-px ramps. Larger patches interpolate the kernel over a longer
distance, though; inside one depth layer the kernel varies with field and
azimuth only (and the layer's narrow depth range), often slowly.

:func:`choose` blurs a sample of the layer's pixels two ways: with the
kernel a candidate (m, b) would give them (the ramp-weighted kernels of the
patches covering them, each at its patch's diopters) and with their own PSF
(their depth, field and azimuth: the per-pixel reference's kernel). The
cheapest candidate, counted in FFT points of the windows the layer needs,
whose RMS difference, relative to the RMS of the blurred values, is at most
``eps`` more than the finest candidate's is chosen.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import fft
from .windows import blend_window, grow_square
from .psfmap import point_kernels

# (patch px, blend half-width px) tried after the finest (the options' patch with the tent)
WIDE = ((32, 8), (64, 8))
SAMPLES = 48            # layer pixels whose kernel is compared


@dataclass(frozen=True)
class PatchChoice:
    """A layer's patch size m (px), blend half-width b (px), and the sampled
    relative RMS error (of the candidates measured) and cost (FFT points) of
    each candidate."""

    m: int
    b: int
    error: dict            # {(m, b): sampled relative RMS error}, the candidates measured
    cost: dict             # {(m, b): FFT points}

    def info(self) -> dict:
        err = self.error.get((self.m, self.b))
        return {"patch": self.m, "blend": self.b, "sampled_rms_error": None if err is None else round(err, 6)}


def candidates(patch: int) -> list[tuple[int, int]]:
    """(m, b): the finest (``patch``, the tent) first, then the wide ones larger than it."""
    return [(patch, patch // 2)] + [(m, b) for m, b in WIDE if m > patch and b <= m // 2]


def sample_pixels(mask: np.ndarray, n: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` pixels (rows, cols) of ``mask`` spread evenly along its
    raster order."""
    flat = np.flatnonzero(mask)
    pick = flat[np.unique(np.linspace(0, len(flat) - 1, min(n, len(flat))).round().astype(np.int64))]
    rows, cols = np.divmod(pick, mask.shape[1])
    return rows, cols


def _covering(y: np.ndarray, m: int, b: int, n_patch: int) -> tuple[np.ndarray, np.ndarray]:
    """For pixels y (n,) along an axis of ``n_patch`` m-px patches: the two
    patches whose windows [i m - b, (i + 1) m + b) may cover them (n, 2) and
    their blend weights (n, 2), renormalised where one lies outside the grid
    (the border window then holds its weight at 1, as the convolution does)."""
    tw = blend_window(m, b)
    near = y // m
    centre = near * m + m / 2.0
    other = np.where(y + 0.5 < centre, near - 1, near + 1)
    idx = np.stack([near, other], -1)
    off = y[:, None] - (idx * m - b)                       # position inside each window
    wgt = np.where((off >= 0) & (off < len(tw)), tw[np.clip(off, 0, len(tw) - 1)], 0.0)
    inside = (idx >= 0) & (idx < n_patch)
    wgt = np.where(inside, wgt, 0.0)
    wgt = wgt / np.maximum(wgt.sum(axis=1, keepdims=True), 1e-12)
    return np.clip(idx, 0, n_patch - 1), wgt


def patch_diopters(inv: np.ndarray, mask: np.ndarray, m: int, rings: int) -> np.ndarray:
    """Each m-px patch's diopters as the blur of the layer ``mask`` sees them
    (nph, npw): the mean of ``inv`` (H, W) over the layer's pixels in it;
    a patch without any takes the mean of its filled neighbours', ring by
    ring up to ``rings`` patches away (as far as the blur reaches), and the
    layer's mean beyond. So the blur spilling out of a layer's edge keeps
    the kernel of the pixels it comes from (not the layer's mean depth: a
    board merged with the floor before it would spill with the floor's)."""
    h, w = mask.shape
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    pad = ((0, nph * m - h), (0, npw * m - w))
    total = np.pad(np.where(mask, inv, 0.0), pad).reshape(nph, m, npw, m).sum(axis=(1, 3))
    count = np.pad(mask, pad).reshape(nph, m, npw, m).sum(axis=(1, 3)).astype(np.float64)
    has = count > 0
    out = np.where(has, total / np.maximum(count, 1.0), 0.0)
    if not has.any():
        return out
    mean = float(total.sum() / count.sum())
    for _ in range(rings):
        if has.all():
            break
        vals, got = np.where(has, out, 0.0), has.astype(np.float64)
        acc, n = vals.copy(), got.copy()
        for axis in (0, 1):                              # a 3 x 3 box sum, rows then columns
            a_, n_ = acc.copy(), n.copy()
            lo, hi = [slice(None)] * 2, [slice(None)] * 2
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            a_[tuple(hi)] += acc[tuple(lo)]
            a_[tuple(lo)] += acc[tuple(hi)]
            n_[tuple(hi)] += n[tuple(lo)]
            n_[tuple(lo)] += n[tuple(hi)]
            acc, n = a_, n_
        new = ~has & (n > 0)
        out = np.where(new, acc / np.maximum(n, 1.0), out)
        has = has | new
    return np.where(has, out, mean)


def fill_rings(kernel_size: int, m: int, b: int) -> int:
    """Patches around a layer that its blur with m-px patches (blend b) reaches."""
    return math.ceil((kernel_size // 2 + b) / m) + 1


def layer_depth(depth: np.ndarray, inv: np.ndarray, mask: np.ndarray, m: int, rings: int) -> np.ndarray:
    """The depth map (metres) a layer's blur is given: its pixels' own depth,
    elsewhere the diopters of ``patch_diopters`` (so every m-px patch's mean
    is its layer pixels' mean)."""
    fill = patch_diopters(inv, mask, m, rings)
    h, w = mask.shape
    up = np.repeat(np.repeat(fill, m, axis=0), m, axis=1)[:h, :w]
    return np.where(mask, depth, np.where(up > 0, 1.0 / np.where(up > 0, up, 1.0), np.inf))


def blended_kernels(library, geometry, inv: np.ndarray, mask: np.ndarray, rows, cols, m: int, b: int) -> np.ndarray:
    """The kernels (n, 3, k, k) the patch-wise blur of the layer ``mask``
    gives pixels (rows, cols): the blend of the kernels of the m-px patches
    of the image grid covering each (blend half-width b), each patch at its
    diopters (``patch_diopters``)."""
    h, w = inv.shape
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    iy, wy = _covering(rows, m, b, nph)
    ix, wx = _covering(cols, m, b, npw)
    pi = np.repeat(iy, 2, axis=1)                          # (n, 4): (row a, col a), (row a, col b), ...
    pj = np.tile(ix, (1, 2))
    wgt = (np.repeat(wy, 2, axis=1) * np.tile(wx, (1, 2))).astype(np.float32)
    key = pi * npw + pj
    uniq, back = np.unique(key, return_inverse=True)
    ui, uj = np.divmod(uniq, npw)
    cy = np.minimum(ui * m + (m - 1) / 2.0, h - 1)
    cx = np.minimum(uj * m + (m - 1) / 2.0, w - 1)
    di = patch_diopters(inv, mask, m, 1)[ui, uj]
    kern = point_kernels(library, geometry, cy, cx, np.where(di > 0, 1.0 / np.where(di > 0, di, 1.0), np.inf))
    return np.einsum("nq,nqcyx->ncyx", wgt, kern[back.reshape(key.shape)])


def gathered(img: np.ndarray, mask: np.ndarray, rows, cols, kernels: np.ndarray) -> np.ndarray:
    """The blur of the layer ``mask`` of ``img`` (H, W, 3) at pixels (rows,
    cols) with their kernels (n, 3, k, k), as the layered bokeh forms it
    (the premultiplied colour with each colour's PSF, the coverage with
    each), zeros beyond the border: (n, 6)."""
    h, w = mask.shape
    r = kernels.shape[-1] // 2
    nb = np.zeros((len(rows), 2 * r + 1, 2 * r + 1, 4), np.float32)
    for n, (y, x) in enumerate(zip(rows, cols)):
        y0, y1, x0, x1 = max(0, y - r), min(h, y + r + 1), max(0, x - r), min(w, x + r + 1)
        a = mask[y0:y1, x0:x1, None]
        nb[n, y0 - y + r:y1 - y + r, x0 - x + r:x1 - x + r] = np.concatenate([img[y0:y1, x0:x1] * a, a], -1)
    nb = nb[:, ::-1, ::-1]                                 # output y reads I(y - (t - r))
    colour = np.einsum("ncyx,nyxc->nc", kernels, nb[..., :3])
    cover = np.einsum("ncyx,nyx->nc", kernels, nb[..., 3])
    return np.concatenate([colour, cover], axis=-1)


def window_cost(has: np.ndarray, m0: int, m: int, b: int, half: int) -> int:
    """FFT points of the m-px windows (blend b, kernels of half-width
    ``half``) that a layer needs: those within the kernel's reach of its
    pixels, from ``has`` (the m0-px patches holding any of them; m a
    multiple of m0)."""
    f = m // m0
    nh, nw = math.ceil(has.shape[0] / f), math.ceil(has.shape[1] / f)
    coarse = np.pad(has, ((0, nh * f - has.shape[0]), (0, nw * f - has.shape[1]))).reshape(nh, f, nw, f).any(axis=(1, 3))
    live = grow_square(coarse, math.ceil((half + b) / m))
    return int(live.sum()) * fft.fast_size(m + 2 * b + 2 * half) ** 2


def choose(library, geometry, img: np.ndarray, mask: np.ndarray, inv: np.ndarray, patch: int,
           eps: float) -> PatchChoice:
    """The patch size and blend of the layer ``mask`` (H, W) of ``img`` (H,
    W, 3) on the image of ``geometry``, ``inv`` (H, W) the diopters of its
    pixels (the layer's mean stands in elsewhere, as the bokeh blurs it):
    the cheapest candidate (``candidates(patch)``) whose RMS error over the
    sampled pixels of the layer, against their own PSFs, is within ``eps``
    (in the image's units); the finest when none is."""
    cands = candidates(patch)
    rows, cols = sample_pixels(mask)
    d = np.where(inv[rows, cols] > 0, 1.0 / np.where(inv[rows, cols] > 0, inv[rows, cols], 1.0), np.inf)
    own = point_kernels(library, geometry, rows, cols, d)
    h, w = mask.shape
    nph, npw = math.ceil(h / patch), math.ceil(w / patch)
    has = np.pad(mask, ((0, nph * patch - h), (0, npw * patch - w))).reshape(nph, patch, npw, patch).any(axis=(1, 3))
    cost = {c: window_cost(has, patch, *c, own.shape[-1] // 2) for c in cands}
    error = {}
    truth = None

    def err(c):
        nonlocal truth
        if c not in error:
            if truth is None:
                truth = gathered(img, mask, rows, cols, own)
            got = gathered(img, mask, rows, cols, blended_kernels(library, geometry, inv, mask, rows, cols, *c))
            error[c] = float(np.sqrt(((got - truth) ** 2).mean() / max(float((truth ** 2).mean()), 1e-30)))
        return error[c]
    for c in sorted(cands, key=lambda c: (cost[c], c[0])):
        if c == cands[0] or err(c) <= eps or err(c) <= eps + err(cands[0]):
            break
    return PatchChoice(*c, error, cost)
