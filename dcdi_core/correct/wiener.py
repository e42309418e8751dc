"""Wiener deconvolution of overlapping windows, one kernel per window.

Each window is the tent-weighted region of one m x m patch (``2m`` pixels
square, as ``render.convolve`` blends the forward blur) with ``pad`` pixels of
context on every side. Its mean is taken out, its outer ``taper`` pixels are
ramped to zero (a window's edges are not periodic; without the ramp the
circular FFT rings into the region kept), and it is divided in the Fourier
domain by its kernel with a gradient prior:

    X = conj(K) Y / (|K|^2 + lambda |D|^2),   |D|^2 = 4 - 2 cos(wx) - 2 cos(wy)

lambda is the noise variance over the image's gradient power (per window and
channel, set by the caller). The kernel sums to 1 and |D|^2 vanishes at DC,
so a constant passes unchanged and the mean goes back as it came.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..parallel import thread_pool, workers
from ..render import fft


# the total-variation threshold per unit of the quadratic prior's weight
# (lambda |D|^2 against |D|): about a typical gradient, px^-1 (tuned by
# `python -m lab report correction`)
TV_SCALE = 0.1


@dataclass(frozen=True)
class WindowLayout:
    m: int            # patch size, px
    pad: int          # context on each side of the 2m core, px
    taper: int        # px of the context ramped to zero at the window's edge

    @property
    def core(self) -> int:
        return 2 * self.m

    @property
    def size(self) -> int:
        return self.core + 2 * self.pad

    @property
    def fft_size(self) -> int:
        return fft.fast_size(self.size)


def layout_for(m: int, kernel_size: int, pad: int | None = None) -> WindowLayout:
    """Context of 1.5 kernel radii by default, its outer half a ramp: a
    defocus kernel's inverse reaches far and a window cut short rings into
    the core, but 3 radii cost 2.6x the time for 0.25 dB or less (`dcdi
    report correction`, MOS-S1 and MOS-S2 at 12.2 um)."""
    r = max(kernel_size // 2, 2)
    pad = (3 * r) // 2 if pad is None else max(int(pad), 2)
    return WindowLayout(m, pad, max(1, pad // 2))


def _ramp(n: int, t: int) -> np.ndarray:
    """1-D weights: a raised-cosine rise over t px at each end, 1 between."""
    x = np.ones(n)
    if t > 0:
        r = 0.5 - 0.5 * np.cos(np.pi * (np.arange(t) + 0.5) / t)
        x[:t], x[n - t:] = r, r[::-1]
    return x


def gradient_power(f: int) -> np.ndarray:
    """|D|^2 on the rfft grid of an f x f transform: 4 - 2 cos wx - 2 cos wy."""
    wy = 2 * np.pi * np.fft.fftfreq(f)
    wx = 2 * np.pi * np.fft.rfftfreq(f)
    return (4.0 - 2.0 * np.cos(wy)[:, None] - 2.0 * np.cos(wx)[None, :]).astype(np.float32)


def kernel_spectra(kernels: np.ndarray, f: int, be: str) -> np.ndarray:
    """rfft2 of (n, C, k, k) kernels centred on pixel (0, 0) of an f x f grid."""
    n, c, k, _ = kernels.shape
    grid = np.zeros((n, c, f, f), np.float32)
    grid[..., :k, :k] = kernels
    grid = np.roll(grid, (-(k // 2), -(k // 2)), axis=(-2, -1))
    return fft.rfft2(grid, (f, f), be)


@dataclass
class _Windows:
    """Windows of a chunk in the Fourier domain, and what their filters need."""

    spec: np.ndarray         # (n, C, f, f//2+1) the tapered windows, means taken out
    k_spec: np.ndarray       # (n, C, f, f//2+1) their kernels
    mean: np.ndarray         # (n, C, 1, 1)
    lam: np.ndarray          # (n, C, 1, 1) the prior's weight
    d2: np.ndarray           # (f, f//2+1) |D|^2


def _windows(padded, origins, kernels, var, weight: float, adaptive: bool, lay: WindowLayout, be: str,
             grad_px=None) -> _Windows:
    """The chunk's windows, kernels and lambda. ``var`` (n, C): the noise
    variance at each window's brightness. lambda = weight x var / A, A the
    image's gradient power: measured in the window when ``adaptive`` (the
    capture's gradient energy less the noise's, over the kernel's: textures
    differ by orders of magnitude between scenes), else 1."""
    L, f = lay.size, lay.fft_size
    ramp = _ramp(L, lay.taper).astype(np.float32)
    taper2d = ramp[:, None] * ramp[None, :]
    rows = origins[:, 0, None] + np.arange(L)[None, :]
    cols = origins[:, 1, None] + np.arange(L)[None, :]
    win = np.moveaxis(padded[rows[:, :, None], cols[:, None, :]], -1, 1).astype(np.float32)   # (n, C, L, L)
    mean = win.mean(axis=(-2, -1), keepdims=True)
    spec = fft.rfft2((win - mean) * taper2d, (f, f), be)
    k_spec = kernel_spectra(kernels, f, be)
    d2 = gradient_power(f)
    var = np.asarray(var, np.float32)[:, :, None, None]
    if adaptive:
        if grad_px is None:
            n_eff = float((taper2d ** 2).sum())
            grad = (np.abs(spec) ** 2 * d2).sum(axis=(-2, -1), keepdims=True) / n_eff
            power = np.maximum(grad - var * d2.sum(), 0.0) / (np.abs(k_spec) ** 2).sum(axis=(-2, -1), keepdims=True)
        else:      # per pixel (Parseval): E|grad y|^2 = A mean|K|^2 + var mean|D|^2
            g = np.asarray(grad_px, np.float32)[:, :, None, None]
            power = np.maximum(g - var * d2.mean(), 0.0) / (np.abs(k_spec) ** 2).mean(axis=(-2, -1), keepdims=True)
        lam = weight * var / np.maximum(power, 1e-12)
    else:
        lam = weight * var
    return _Windows(spec, k_spec, mean, lam.astype(np.float32), d2)


def _cores(x_spec, w: _Windows, lay: WindowLayout, be: str) -> np.ndarray:
    f, p = lay.fft_size, lay.pad
    out = fft.irfft2(x_spec, (f, f), be)[..., p:p + lay.core, p:p + lay.core]
    return (out + w.mean).astype(np.float32)


def deconvolve_windows(w: _Windows, lay: WindowLayout, be: str) -> np.ndarray:
    """Wiener-deconvolved cores (n, C, 2m, 2m)."""
    filt = np.conj(w.k_spec) / (np.abs(w.k_spec) ** 2 + w.lam * w.d2)
    return _cores(w.spec * filt, w, lay, be)


def deconvolve_all(padded, origins, kernels, var, lay: WindowLayout, be: str, *, weight: float, adaptive: bool,
                   chunk: int = 64, on_chunk=None, iterations: int = 0, grad_px=None) -> np.ndarray:
    """Cores (n, C, 2m, 2m) of every window: Wiener (``iterations`` 0) or
    ``hqs_windows``, chunks of windows on the shared pool;
    ``on_chunk(done, total)`` after each."""
    n = len(origins)
    out = np.empty((n, padded.shape[-1], lay.core, lay.core), np.float32)
    starts = list(range(0, n, chunk))

    def work(s):
        sl = slice(s, min(s + chunk, n))
        w = _windows(padded, origins[sl], kernels[sl], var[sl], weight, adaptive, lay, be,
                     None if grad_px is None else grad_px[sl])
        out[sl] = hqs_windows(w, lay, be, iterations) if iterations else deconvolve_windows(w, lay, be)
        return sl.stop - sl.start

    done = 0
    if workers() > 1 and len(starts) > 1:
        for k in thread_pool().map(work, starts):
            done += k
            if on_chunk:
                on_chunk(done, n)
    else:
        for s in starts:
            done += work(s)
            if on_chunk:
                on_chunk(done, n)
    return out


def hqs_windows(w: _Windows, lay: WindowLayout, be: str, iterations: int = 4, beta0: float = 4.0) -> np.ndarray:
    """Cores (n, C, 2m, 2m) restored by half-quadratic splitting with a
    total-variation prior (anisotropic L1 of the gradients): the Wiener step
    alternated with soft thresholding of the gradients, the splitting weight
    doubling from ``beta0`` x lambda. The prior keeps edges the quadratic
    one blurs; each iteration costs three FFTs of the window."""
    f = lay.fft_size
    wy = 2 * np.pi * np.fft.fftfreq(f)[:, None]
    wx = 2 * np.pi * np.fft.rfftfreq(f)[None, :]
    dy, dx = (np.exp(1j * wy) - 1).astype(np.complex64), (np.exp(1j * wx) - 1).astype(np.complex64)
    kty, k2 = np.conj(w.k_spec) * w.spec, np.abs(w.k_spec) ** 2
    x_spec = kty / (k2 + w.lam * w.d2)                                # the Wiener start
    beta = beta0 * w.lam
    for _ in range(iterations):
        x = fft.irfft2(x_spec, (f, f), be)
        gy, gx = np.roll(x, -1, axis=-2) - x, np.roll(x, -1, axis=-1) - x   # the gradients D applies
        t = TV_SCALE * w.lam / beta
        zy = np.sign(gy) * np.maximum(np.abs(gy) - t, 0.0)
        zx = np.sign(gx) * np.maximum(np.abs(gx) - t, 0.0)
        rhs = kty + beta * (np.conj(dy) * fft.rfft2(zy, (f, f), be) + np.conj(dx) * fft.rfft2(zx, (f, f), be))
        x_spec = rhs / (k2 + beta * w.d2)
        beta = beta * 2.0
    return _cores(x_spec, w, lay, be)
