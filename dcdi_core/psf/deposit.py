"""Ray energy onto sensor pixels: each ray's energy into the pixel it lands in,
optionally spread by a Gaussian against ray-count noise.

What the kernel must contain. A sensor pixel records the irradiance
integrated over its area: S = box * PSF * I (I the scene's ideal image, box
the pixel aperture). The all-in-focus image the kernel is applied to is
area-integrated already (a Blender render with a 1-px box pixel filter, or
any sensor): A = box * I. So S = PSF * A: the kernel is the optical PSF
alone, with no second pixel aperture. On the pixel grid the kernel is
K(n) = integral of PSF(x) phi(n - x) dx, phi the reconstruction of A between
its samples; the ray histogram over pixels (phi = the 1-px box, sigma = 0
here) is the choice that is non-negative, conserves every ray's energy and
is exact for a perfect lens (all rays at the chief ray, which is the kernel
centre: K is the identity and a sharp image stays as it is). For a PSF
wider than a pixel its residual is one 1-px box (variance 1/12 px^2; the
smallest of any non-negative, energy-conserving deposit), where the paper's
deposit below adds 2/9 + 1/12 px^2.

The paper's deposit (``sigma_px = sqrt(2) / 3``): every ray spreads its
energy with an isotropic Gaussian of sigma = sqrt(dh^2 + dw^2) / 3 (dh, dw
the pixel size), and a pixel receives the Gaussian's integral over its
area. A smaller sigma trades bias for ray-count noise; `python -m lab report
simulation-accuracy` measures it against rays. Because the Gaussian is the
same for every ray and separable, the deposit is computed as

    PSF = M . H . M^T

where H is a histogram of the rays on a grid ``oversample`` times finer than
the pixels (bincount: one pass over the rays), and M[i, j] is the integral
over pixel i of a Gaussian centred on fine cell j (erf differences). M is
banded (a cell reaches 3 pixels either side of its own) and depends only on
the cell's phase within its pixel, so it is applied as 7 taps per phase on
the rows, then on the columns, of the region the rays reach. The only
approximation is the ray position's quantisation to 1/oversample pixel, which
adds a variance of 1/(12 oversample^2) px^2 (0.5 % of sigma^2 at oversample 9;
an odd oversample puts pixel centres on bin centres, so a ray at a pixel
centre is deposited exactly);
`python -m lab report psf-accuracy` measures it.

Kernel coordinates: index [i, j] is row i along sensor +y, column j along
sensor +x, the centre pixel (k // 2, k // 2) centred on the kernel origin.
"""
from __future__ import annotations

import math

import numpy as np

from .. import caches

# rays reaching up to this many pixels outside the k x k window still deposit
# their Gaussian tail inside it (3 sigma < 1.5 px)
MARGIN_PX = 2


def gaussian_sigma_px() -> float:
    """The paper's deposit width for square pixels, in pixels: sqrt(2) / 3."""
    return math.sqrt(2.0) / 3.0


def _box_deposit(hist_fine: np.ndarray, s: int) -> np.ndarray:
    """(C, NY s, NX s) fine histogram -> (C, NY + 2 T, NX + 2 T) pixel sums,
    laid out like the Gaussian path's output (T empty pixels each side)."""
    c, nys, nxs = hist_fine.shape
    ny, nx = nys // s, nxs // s
    out = np.zeros((c, ny + 2 * TAPS_PX, nx + 2 * TAPS_PX))
    out[:, TAPS_PX:TAPS_PX + ny, TAPS_PX:TAPS_PX + nx] = hist_fine.reshape(c, ny, s, nx, s).sum(axis=(2, 4))
    return out


# a fine cell's Gaussian reaches this many pixels either side of its own
# pixel (beyond: < 1e-10 of its energy at sigma = sqrt(2)/3 px)
TAPS_PX = 3


@caches.lru("deposit phase taps", maxsize=16)
def phase_taps(oversample: int, sigma_px: float) -> np.ndarray:
    """g (oversample, 2 T + 1): energy that pixel (own + t - T) receives from a
    unit ray in fine cell of phase p within its own pixel (erf differences)."""
    u = (np.arange(oversample) + 0.5) / oversample               # cell centres within the pixel
    t = np.arange(-TAPS_PX, TAPS_PX + 2, dtype=np.float64)       # pixel edges, relative
    z = (t[None, :] - u[:, None]) / (sigma_px * math.sqrt(2.0))
    cdf = 0.5 * (1.0 + np.vectorize(math.erf)(z))
    g = cdf[:, 1:] - cdf[:, :-1]
    g.setflags(write=False)
    return g


def _blur_rows(h: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """(C, NY * s, X) fine rows -> (C, NY + 2 T, X) pixel rows: each fine row
    spreads over the 2 T + 1 pixels around its own with its phase's taps."""
    c, nys, x = h.shape
    s, nt = taps.shape
    ny = nys // s
    a = np.einsum("cypx,pt->ctyx", h.reshape(c, ny, s, x), taps, optimize=True)
    out = np.zeros((c, ny + nt - 1, x))
    for t in range(nt):
        out[:, t:t + ny] += a[:, t]
    return out


# a ray's footprint (its pupil cell on the sensor) is drawn when it spans at
# least this many pixels (below, the histogram's moire is under 25 % of a
# pixel's share and the kernel is small)
FOOTPRINT_MIN_PX = 0.25


def _overlaps(u: np.ndarray, width: float, n: int):
    """The pixels (index arrays, one per offset) a box of ``width`` px centred
    at ``u`` (pixel coordinates: pixel j spans [j, j + 1)) overlaps, and the
    fraction of the box each holds; ``n`` offsets cover any box's pixels."""
    lo, hi = u - width / 2.0, u + width / 2.0
    first = np.floor(lo)
    out = []
    for o in range(n):
        j = first + o
        frac = (np.minimum(hi, j + 1.0) - np.maximum(lo, j)) / width
        out.append((j.astype(np.int64), np.maximum(frac, 0.0)))
    return out


def _footprint_deposit(x: np.ndarray, y: np.ndarray, wl: np.ndarray, width: float, k: int,
                       channel_weights: np.ndarray) -> np.ndarray:
    """(3, k, k): each ray's energy spread evenly over a square of side
    ``width`` px centred on it, integrated over each pixel (exactly: the
    square's overlap with the pixel); x, y the rays' positions relative to
    the kernel's centre (px), wl their wavelength index. A square wider than
    :data:`FOOTPRINT_EXACT_PX` (rays sparse across a wide blur: a preview's
    few rays, a coarse level's) is drawn as the rays' histogram spread by a
    moving sum of the nearest odd number of pixels: the cost stays one pass
    over the rays and a few over the window, where the exact overlaps would
    cost the square's area in pixels per ray."""
    w = channel_weights.shape[0]
    if width > FOOTPRINT_EXACT_PX:
        return _wide_footprint(x, y, wl, width, k, channel_weights)
    n = int(math.ceil(width)) + 1
    c = k / 2.0
    jx, fx = (np.stack(a) for a in zip(*_overlaps(x + c, width, n)))      # (n, rays) each
    jy, fy = (np.stack(a) for a in zip(*_overlaps(y + c, width, n)))
    # every (row offset, column offset) pair of every ray, binned in one pass
    ok = ((jx >= 0) & (jx < k) & (fx > 0))[None, :, :] & ((jy >= 0) & (jy < k) & (fy > 0))[:, None, :]
    idx = (jy[:, None, :] * k + jx[None, :, :]) * w + wl[None, None, :]
    wts = fy[:, None, :] * fx[None, :, :]
    hist = np.bincount(idx[ok], weights=wts[ok], minlength=k * k * w)
    return (hist.reshape(k * k, w) @ channel_weights).T.reshape(3, k, k)


# a footprint up to this wide (px) is integrated exactly over the pixels (at most 16 per ray); a wider one
# is a moving sum over the rays' histogram, its side rounded to an odd number of pixels
FOOTPRINT_EXACT_PX = 3.0


def _moving_sum(a: np.ndarray, n: int, axis: int) -> np.ndarray:
    """Centred moving sum of odd width ``n`` along ``axis``, zeros beyond the ends."""
    h = n // 2
    pad = [(0, 0)] * a.ndim
    pad[axis] = (h + 1, h)
    c = np.cumsum(np.pad(a, pad), axis=axis)
    m = a.shape[axis]
    return np.take(c, np.arange(n, n + m), axis=axis) - np.take(c, np.arange(m), axis=axis)


def _wide_footprint(x, y, wl, width: float, k: int, channel_weights: np.ndarray) -> np.ndarray:
    """(3, k, k): the rays' pixel histogram over the window grown by half the
    square, spread by an n x n moving sum (n the odd number of pixels
    nearest ``width``), cropped to the window."""
    w = channel_weights.shape[0]
    n = max(1, int(round((width - 1.0) / 2.0)) * 2 + 1)
    h = n // 2
    g = k + 2 * h
    jx = np.floor(x + k / 2.0).astype(np.int64) + h
    jy = np.floor(y + k / 2.0).astype(np.int64) + h
    ok = (jx >= 0) & (jx < g) & (jy >= 0) & (jy < g)
    hist = np.bincount((jy[ok] * g + jx[ok]) * w + wl[ok], minlength=g * g * w).astype(np.float64)
    grid = (hist.reshape(g * g, w) @ channel_weights).T.reshape(3, g, g)
    spread = _moving_sum(_moving_sum(grid, n, 1), n, 2) / float(n * n)
    return spread[:, h:h + k, h:h + k]


def deposit(x_px, y_px, valid, channel_weights, k: int, oversample: int, sigma_px: float,
            footprint_px=None):
    """Deposit of rays into (B, 3, k, k) kernels: ``sigma_px`` 0 puts each
    ray into the pixel it lands in (the ray histogram; ``oversample`` is then
    irrelevant), > 0 spreads it by a Gaussian of that width (pixels)
    integrated over each pixel.

    x_px, y_px: (B, W, P) ray positions in pixels relative to the kernel
    centre; valid: (B, W, P) bool; channel_weights: (W, 3), the energy of one
    ray of wavelength w in channel c. Returns float64 (B, 3, k, k), not
    normalised (a ray's energy is its weight).

    Each kernel's histogram covers only the fine cells its rays reach (most
    PSFs are far smaller than the window), so the cost follows the blur.

    footprint_px: (B,) the rays' spacing on the sensor (pixels), or None.
    With the histogram (``sigma_px`` 0), where it is at least
    :data:`FOOTPRINT_MIN_PX`, each ray's energy is spread evenly over a
    square of that side centred on it (the pupil cell it stands for, on the
    sensor), integrated exactly over each pixel: a regular grid of rays then
    covers a uniformly lit blur evenly, where the histogram alone beats the
    ray grid against the pixel grid (moire of relative amplitude about the
    spacing in pixels). The square's variance, side^2 / 12, vanishes as rays
    are added."""
    b, w, p = x_px.shape
    half = k / 2.0 + MARGIN_PX
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"deposit sigma_px = {sigma_px!r}: allowed a finite number >= 0 (pixels)")
    taps = phase_taps(oversample, float(sigma_px)) if sigma_px > 0 else None
    if taps is None:
        oversample = 1          # whole pixels: sub-pixel cells would only be summed again
    spread = np.zeros(b) if footprint_px is None or taps is not None else \
        np.nan_to_num(np.broadcast_to(np.asarray(footprint_px, np.float64), (b,)), nan=0.0, posinf=0.0)
    # no wider than the window (a wider one is no pupil cell's image)
    spread = np.where(spread >= FOOTPRINT_MIN_PX, np.minimum(spread, float(k)), 0.0)
    g = (k + 2 * MARGIN_PX) * oversample
    out = np.zeros((b, 3, k, k))
    wl_index = np.broadcast_to(np.arange(w)[:, None], (w, p))
    # fine-cell indices for the whole batch at once (truncation is floor for
    # the rays kept: those right of and below the window's origin)
    fx = ((x_px + half) * oversample).astype(np.int64)
    fy = ((y_px + half) * oversample).astype(np.int64)
    inside = valid & (x_px > -half) & (y_px > -half) & (fx < g) & (fy < g)
    s = oversample
    for i in range(b):
        if spread[i] > 0:
            v = valid[i]
            out[i] = _footprint_deposit(x_px[i][v], y_px[i][v], wl_index[v], float(spread[i]), k, channel_weights)
            continue
        ins = inside[i]
        if not ins.any():
            continue
        fxi, fyi = fx[i][ins], fy[i][ins]
        # the crop: whole pixels (of the window extended by MARGIN_PX) that rays reach
        px0, px1 = int(fxi.min()) // s, int(fxi.max()) // s + 1
        py0, py1 = int(fyi.min()) // s, int(fyi.max()) // s + 1
        nx, ny = (px1 - px0) * s, (py1 - py0) * s
        idx = ((fyi - py0 * s) * nx + (fxi - px0 * s)) * w + wl_index[ins]
        hist = np.bincount(idx, minlength=ny * nx * w).reshape(ny * nx, w).astype(np.float64)
        hc = (hist @ channel_weights).T.reshape(3, ny, nx)
        if taps is None:
            both = _box_deposit(hc, s)
        else:
            rows = _blur_rows(hc, taps)                                   # (3, NY + 2T, nx)
            both = _blur_rows(rows.transpose(0, 2, 1), taps).transpose(0, 2, 1)
        # place: extended pixel P is kernel pixel P - MARGIN_PX; the blur starts T before the crop
        oy, ox = py0 - TAPS_PX - MARGIN_PX, px0 - TAPS_PX - MARGIN_PX
        ky0, kx0 = max(oy, 0), max(ox, 0)
        ky1, kx1 = min(oy + both.shape[1], k), min(ox + both.shape[2], k)
        if ky1 > ky0 and kx1 > kx0:
            out[i, :, ky0:ky1, kx0:kx1] = both[:, ky0 - oy:ky1 - oy, kx0 - ox:kx1 - ox]
    return out
