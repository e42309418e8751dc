"""Resampling an image at fractional pixel positions (numpy only).

Conventions (as :mod:`.geometry`): pixel centres sit at integer positions,
``y`` is the row (row 0 at the top), ``x`` the column (column 0 at the
left), both in pixels. Every method sees the image extended by repeating
its edge pixels, and holds its value constant beyond the outer pixel
centres: a position is clamped to [0, H - 1] x [0, W - 1] before it is
interpolated (no jump where the clamp begins, since every method below
passes through the samples at integer positions).

Methods (the kernel's support in pixels, per axis):

* ``"nearest"`` (1 tap): the sample whose centre is nearest, halves rounded
  up; never mixes values, for depth maps and labels.
* ``"linear"`` (2 taps): bilinear, float32 arithmetic.
* ``"keys"`` (4 taps): Keys' cubic convolution with a = -0.5, which
  reproduces polynomials up to degree 2.
* ``"lanczos3"`` (6 taps): sinc(s) sinc(s / 3), weights normalised to sum 1
  per axis. It reproduces constants but not ramps: on a ramp of slope g
  (value per pixel) it is off by up to 0.020 g (a phase error of the
  truncated sinc, largest at fractions 0.2 and 0.8 of a pixel).
* ``"bspline"`` (4 taps): interpolating cubic B-spline. The image is first
  turned into spline coefficients by the exact inverse filter of the
  B-spline's sampled kernel (pole sqrt(3) - 2), with the edge-repeated
  extension summed in closed form; this is what
  ``scipy.ndimage.map_coordinates(order=3, mode="nearest")`` computes
  for positions inside the image (scipy pads 12 edge samples instead of
  summing the extension; its coefficients agree to 4e-15 in float64).
  Reproduces cubics away from the edges.

Work is done in chunks of consecutive output positions (rows of the
output, for a 2-D ``y``) so that the temporaries stay near
``_CHUNK_BYTES``, and the B-spline prefilter in blocks of ``_FILTER_BYTES``,
whatever the image size; the output and one float32 copy of the image, by
channel (spline coefficients for ``"bspline"``), come on top: measured
peak 175 MB, of which 84 MB the output, for 1280 x 1920 x 9 float32.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import InputRangeError

METHODS = ("nearest", "linear", "keys", "lanczos3", "bspline")

# bytes of temporaries one chunk of output positions may use: small enough
# for the accumulators to stay in cache (measured 1.5-2x faster than 64 MiB)
_CHUNK_BYTES = 8 << 20
# bytes of one float64 block of the B-spline prefilter: large, since its
# recursion costs a Python step per row (or column) of each block
_FILTER_BYTES = 64 << 20

_POLE = math.sqrt(3.0) - 2.0      # of the cubic B-spline's inverse filter


# ------------------------------------------------------------------ weights
# Each takes the fractional part t in [0, 1) (float64, 1-D) of a position
# and returns the weights of the taps at floor(position) + first, + first + 1, ...
def _linear_weights(t):
    # float32 from the start: bit-identical to the former distortion._bilinear
    t32 = t.astype(np.float32)
    return [1.0 - t32, t32]


def _keys_weights(t):
    t2, t3 = t * t, t * t * t
    return [-0.5 * t3 + t2 - 0.5 * t,
            1.5 * t3 - 2.5 * t2 + 1.0,
            -1.5 * t3 + 2.0 * t2 + 0.5 * t,
            0.5 * t3 - 0.5 * t2]


def _lanczos3_weights(t):
    # sinc(s) sinc(s / 3) = 3 sin(pi s) sin(pi s / 3) / (pi s)^2 with s = t - k;
    # sin(pi (t - k)) = (-1)^k sin(pi t), and sin(pi (t - k) / 3) by the angle
    # difference: three transcendental calls per position instead of twelve
    common = (3.0 / np.pi ** 2) * np.sin(np.pi * t)
    sin_a, cos_a = np.sin(np.pi * t / 3.0), np.cos(np.pi * t / 3.0)
    out = []
    for k in range(-2, 4):
        s = t - k
        if k == 0:
            # the only zero distance (t = 0), where the kernel is 1
            safe = np.where(s != 0.0, s, 1.0)
            out.append(np.where(s != 0.0, common * sin_a / (safe * safe), 1.0))
            continue
        c, d = math.cos(math.pi * k / 3), math.sin(math.pi * k / 3)
        out.append(((-1.0) ** k * common) * (c * sin_a - d * cos_a) / (s * s))
    total = sum(out)
    return [w / total for w in out]


def _bspline_weights(t):
    u = 1.0 - t
    t3 = t * t * t
    return [u * u * u / 6.0,
            (3.0 * t3 - 6.0 * t * t + 4.0) / 6.0,
            (-3.0 * t3 + 3.0 * t * t + 3.0 * t + 1.0) / 6.0,
            t3 / 6.0]


# name: (offset of the first tap from floor(position), number of taps, weights)
_KERNELS = {
    "linear": (0, 2, _linear_weights),
    "keys": (-1, 4, _keys_weights),
    "lanczos3": (-2, 6, _lanczos3_weights),
    "bspline": (-1, 4, _bspline_weights),
}


# -------------------------------------------------------- B-spline prefilter
def _spline_coefficients(f: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients along axis 0 of float64 samples ``f``
    (N, M, ...), at least 2-D (the recursion runs in place on its rows), for
    the signal extended by repeating f[0] and f[N - 1]; returns
    (N + 2, M, ...): the coefficients at -1 and N included, which the 4 taps
    reach from positions in [0, N - 1]."""
    n = f.shape[0]
    out = np.empty((n + 2,) + f.shape[1:])
    if n == 1:
        out[:] = f[0]                 # a constant signal is its own spline
        return out
    z = _POLE
    c = out[1:-1]
    # causal pass; its start sums z^k f[-k] over the repeated f[0]: f[0] / (1 - z)
    c[0] = f[0] / (1.0 - z)
    for i in range(1, n):
        np.multiply(c[i - 1], z, out=c[i])
        c[i] += f[i]
    # anti-causal pass; its start -sum_k z^(k+1) c+[N-1+k] over the causal
    # output continued into the repeated f[N-1], which tends geometrically to
    # a = f[N-1] / (1 - z)
    a = f[-1] / (1.0 - z)
    c[-1] = -z * (a / (1.0 - z) + (c[-1] - a) / (1.0 - z * z))
    for i in range(n - 2, -1, -1):
        np.subtract(c[i + 1], c[i], out=c[i])
        c[i] *= z
    c *= 6.0                          # the filter's gain, (1 - z)(1 - 1/z)
    # beyond the ends, from the interpolation condition (c[-1] + 4 c[0] + c[1]) / 6 = f[0]
    out[0] = 6.0 * f[0] - 4.0 * c[0] - c[1]
    out[-1] = 6.0 * f[-1] - 4.0 * c[-1] - c[-2]
    return out


def _prefilter(planes: np.ndarray) -> np.ndarray:
    """(C, H, W) image planes -> (C, H + 2, W + 2) float32 spline
    coefficients, filtered in float64 blocks of columns, then of rows (each
    pass vectorised over the channels and the block)."""
    ch, h, w = planes.shape
    coef = np.empty((ch, h + 2, w + 2), np.float32)
    cols = max(1, _FILTER_BYTES // (16 * (h + 2) * ch))
    for c0 in range(0, w, cols):
        c1 = min(c0 + cols, w)
        blk = planes[:, :, c0:c1].astype(np.float64).transpose(1, 0, 2)
        coef[:, :, 1 + c0:1 + c1] = _spline_coefficients(blk).transpose(1, 0, 2)
    rows = max(1, _FILTER_BYTES // (16 * (w + 2) * ch))
    for r0 in range(0, h + 2, rows):
        blk = coef[:, r0:r0 + rows, 1:-1].astype(np.float64).transpose(2, 0, 1)
        coef[:, r0:r0 + rows] = _spline_coefficients(blk).transpose(1, 2, 0)
    return coef


# ------------------------------------------------------------------ sampling
def _axis_taps(pos, size, method, pad):
    """Grid indices and float32 weights of the taps along one axis of
    ``size`` samples; ``pad`` extra grid entries lie before the first sample."""
    first, n_taps, weights = _KERNELS[method]
    p = np.clip(pos, 0.0, size - 1.0)
    i0 = np.minimum(np.floor(p).astype(np.intp), size - 1)
    w = weights(p - i0)
    idx = [np.clip(i0 + (first + k + pad), 0, size + 2 * pad - 1) for k in range(n_taps)]
    return idx, [np.asarray(wk, np.float32) for wk in w]


def _separable(planes, iy, wy, ix, wx):
    """sum_i wy_i sum_j wx_j grid[iy_i, ix_j], grid channels as planes
    (C, rows, cols); returns (C, n). The sums run in tap order, x inside,
    so that "linear" rounds as the former _bilinear did."""
    ch, _, gw = planes.shape
    flat = planes.reshape(ch, -1)
    n = iy[0].size
    out = np.zeros((ch, n), np.float32)
    row = np.empty((ch, n), np.float32)
    term = np.empty(n, np.float32)
    for ri, wyi in zip(iy, wy):
        base = ri * gw
        for j, (cj, wxj) in enumerate(zip(ix, wx)):
            idx = base + cj
            for c in range(ch):
                # 1-D gathers, one channel at a time: several times faster
                # than gathering (n, C) rows
                flat[c].take(idx, out=term)
                term *= wxj
                if j == 0:
                    row[c] = term
                else:
                    row[c] += term
        row *= wyi
        out += row
    return out


def _sample_chunk(planes, y, x, method):
    _, h, w = planes.shape
    if method == "nearest":
        i = np.clip(np.floor(y + 0.5), 0, h - 1).astype(np.intp)
        j = np.clip(np.floor(x + 0.5), 0, w - 1).astype(np.intp)
        return planes.reshape(planes.shape[0], -1).take(i * w + j, axis=1)
    pad = 1 if method == "bspline" else 0
    iy, wy = _axis_taps(y, h - 2 * pad, method, pad)
    ix, wx = _axis_taps(x, w - 2 * pad, method, pad)
    return _separable(planes, iy, wy, ix, wx)


def _positions(y, x):
    y = np.asarray(y, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    if y.shape != x.shape:
        raise InputRangeError("x shape", x.shape, f"{y.shape}, the shape of y")
    for name, v in (("y", y), ("x", x)):
        bad = int(np.count_nonzero(~np.isfinite(v)))
        if bad:
            raise InputRangeError(name, f"{bad} non-finite value(s)", "finite pixel positions")
    return y, x


def _planes(img):
    """(C, H, W) view of the image's channels (C = 1 for a 2-D image)."""
    a = np.asarray(img)
    if a.ndim not in (2, 3) or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputRangeError("img shape", a.shape, "(H, W) or (H, W, C) with H, W >= 1")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputRangeError("img dtype", a.dtype, "a real float (or integer) dtype")
    return a[None] if a.ndim == 2 else a.transpose(2, 0, 1)


def sample(img, y, x, method: str = "linear") -> np.ndarray:
    """Samples of ``img`` at fractional pixel positions (``y``, ``x``).

    img: (H, W) or (H, W, C), any real dtype. y, x: row and column positions
    in pixels (pixel centres at integers, row 0 at the top), arrays of one
    shape, any shape. Positions outside [0, H - 1] x [0, W - 1] take the
    value at the nearest edge (the image is extended by repeating its edge
    pixels). method: one of :data:`METHODS` (see the module docstring).

    Returns float32 of shape ``y.shape`` (+ ``(C,)`` for a 3-D image).
    Raises InputRangeError for an unknown method, non-finite positions
    (naming ``y`` or ``x``) or positions of different shapes."""
    if method not in METHODS:
        raise InputRangeError("method", method, "one of " + ", ".join(METHODS))
    planes = _planes(img)
    y, x = _positions(y, x)
    ch = planes.shape[0]
    if method == "bspline":
        grid = _prefilter(planes)
    else:
        grid = np.ascontiguousarray(planes, dtype=np.float32)
    yf, xf = y.reshape(-1), x.reshape(-1)
    n_taps = 1 if method == "nearest" else _KERNELS[method][1]
    # per position: three float32 accumulators per channel, and per axis and
    # tap an index and a weight, plus float64 scratch for positions and weights
    per_position = 12 * ch + 2 * n_taps * (8 + 4 + 8) + 64
    step = max(1, _CHUNK_BYTES // per_position)
    out = np.empty((yf.size, ch), np.float32)
    for s in range(0, yf.size, step):
        out[s:s + step] = _sample_chunk(grid, yf[s:s + step], xf[s:s + step], method).T
    return out.reshape(y.shape + ((ch,) if np.ndim(img) == 3 else ()))
