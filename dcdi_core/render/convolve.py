"""Spatially varying convolution: every m x m patch of the image with its own kernel.

As in the paper, each patch's output is the image convolved with that
patch's kernel. To leave no seam, neighbouring patches' results are blended:
every patch computes its result over a window reaching ``blend`` pixels into
its neighbours (default m/2: a 2m x 2m window weighted by a tent, the
bilinear partition of unity over the patch centres), and the windows are
added up. So the output varies smoothly between patch centres; a
constant image stays exactly constant (every kernel sums to 1 and the
windows sum to 1). Borders: the image is reflect-padded by the kernel
radius (light from just outside the frame comes in as from a mirror, no dark
rim); padding patches use their nearest patch's kernel.

Each window is convolved by FFT (input 2m + k - 1 wide); windows whose kernel
is the identity are copied, windows whose input is all zero are skipped, and
the FFTs run on the thread pool.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..parallel import thread_pool
from . import fft


def blend_window(m: int, b: int) -> np.ndarray:
    """The 1-D weights (m + 2b,) of a patch over pixels [i m - b, (i + 1) m + b):
    1 inside, linear ramps 2b wide across each border, so that neighbouring
    windows sum to 1. b = m/2 is the tent (bilinear blend of patch results)."""
    x = np.arange(m + 2 * b) + 0.5 - b                  # pixel centre relative to the patch's first pixel
    rise = np.clip((x + b) / (2 * b), 0.0, 1.0)
    fall = np.clip((m + b - x) / (2 * b), 0.0, 1.0)
    return np.minimum(rise, fall)


def rings_needed(kernels: np.ndarray, ring: np.ndarray, eps: float, channels=None) -> np.ndarray:
    """Smallest ring index h such that the pixels with ``ring`` > h hold at most
    ``eps`` of the energy of every channel (of ``channels``, default all), per
    kernel: kernels (..., C, k, k), non-negative as PSFs are (energies add up
    ring by ring); ring (k, k) int >= 0 -> (...) int. eps = 0 keeps every
    nonzero pixel."""
    k = kernels.shape[-1]
    ring = np.asarray(ring, np.int64).ravel()
    n_ring = int(ring.max()) + 1
    onehot = (ring[:, None] == np.arange(n_ring)[None, :]).astype(np.float32)     # (k^2, rings)
    flat = np.asarray(kernels, np.float32).reshape(-1, k * k)      # a view: no copy of the kernels
    per_ring = (flat @ onehot).reshape(*kernels.shape[:-2], n_ring)
    if channels is not None:
        per_ring = per_ring[..., np.unique(channels), :]
    total = per_ring.sum(axis=-1, keepdims=True)
    # energy beyond ring h: rings h + 1 .. last (0 at the last ring exactly)
    outside = np.zeros_like(per_ring)
    outside[..., :-1] = np.cumsum(per_ring[..., :0:-1], axis=-1)[..., ::-1]
    over = outside > eps * total + (0.0 if eps > 0 else 1e-12 * total)
    return over.any(axis=-2).sum(axis=-1)              # the outside shrinks as h grows


def kernel_support(kernels: np.ndarray, eps: float, channels=None) -> np.ndarray:
    """Half-width h (px) of the centred (2h + 1)^2 square that holds all but
    ``eps`` of every channel's energy, per kernel (see ``rings_needed``)."""
    r = kernels.shape[-1] // 2
    d = np.abs(np.arange(-r, r + 1))
    return rings_needed(kernels, np.maximum(d[:, None], d[None, :]), eps, channels)


def patch_convolve(image: np.ndarray, kernels: np.ndarray, m: int, *, identity: np.ndarray | None = None,
                   blend: int | None = None, support_eps: float = 1e-3, pairs=None,
                   chunk: int = 384, fft_backend: str | None = None) -> np.ndarray:
    """Convolve ``image`` (H, W, C) with one kernel per m x m patch.

    kernels: (nph, npw, C, k, k) with nph = ceil(H / m), npw = ceil(W / m),
    k odd, centred on (k // 2, k // 2), rows along image rows. identity:
    optional (nph, npw) bool, patches to copy. blend: half-width b (px) of
    the ramps between neighbouring patches' results (default m / 2, the
    tent); smaller is faster (windows m + 2b) and blends over 2b pixels.
    support_eps: each kernel is cropped to the centred square that holds all
    but this fraction of every channel's energy (then rescaled to its former
    sum, so a constant image stays constant), and windows are grouped by the
    FFT size their crop needs; 0 crops only exact zeros (see ``dcdi report
    simulation-accuracy`` for error against time). pairs: the output
    channels as (image channel, kernel channel) pairs (default: channel c of
    the image with kernel channel c); each distinct image and kernel channel
    is transformed once (the bokeh blurs one coverage channel with the three
    colour PSFs this way). fft_backend: 'scipy' (float32) or 'numpy'
    (float64), default the fastest installed (``fft.backend``). Returns
    float32 (H, W, len(pairs))."""
    img = np.asarray(image, dtype=np.float32)
    h, w, c_in = img.shape
    if m < 2 or m % 2:
        raise ValueError(f"patch size must be even and >= 2, got {m}")
    b = m // 2 if blend is None else int(blend)
    if not 1 <= b <= m // 2:
        raise ValueError(f"blend must be in [1, {m // 2}] px, got {blend}")
    if not 0.0 <= support_eps < 0.5:
        raise ValueError(f"support_eps must be in [0, 0.5), got {support_eps}")
    be = fft.backend(fft_backend)
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    k = kernels.shape[-1]
    pr = np.array([(i, i) for i in range(c_in)] if pairs is None else pairs, int).reshape(-1, 2)
    kc = kernels.shape[2] if kernels.ndim == 5 else -1
    if (kernels.shape[:2] != (nph, npw) or kernels.shape[-2] != k or k % 2 == 0 or len(pr) == 0
            or not ((0 <= pr) & (pr < [c_in, kc])).all()):
        raise ValueError(f"kernels must be ({nph}, {npw}, C, k, k) with k odd, and pairs (image channel, kernel "
                         f"channel) within the image's {c_in} and the kernels' channels; got {kernels.shape}, "
                         f"pairs {pairs}")
    c = len(pr)
    in_used, in_of = np.unique(pr[:, 0], return_inverse=True)        # transform each input channel once
    k_used, k_of = np.unique(pr[:, 1], return_inverse=True)          # and each kernel channel once
    plain_pairs = (np.array_equal(in_of, np.arange(c)) and np.array_equal(k_of, np.arange(c)))
    r = k // 2
    # pad by whole patches (>= r) so that padded patches line up with the image's
    pp = m * math.ceil(r / m)
    mode = "reflect" if min(h, w) > 1 else "edge"
    padded = np.pad(img, ((pp, pp + nph * m - h), (pp, pp + npw * m - w), (0, 0)), mode=mode)
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    ip = np.clip(np.arange(qh) - pp // m, 0, nph - 1)         # padding patches take their nearest patch's kernel
    jp = np.clip(np.arange(qw) - pp // m, 0, npw - 1)
    ident = np.zeros((nph, npw), bool) if identity is None else np.asarray(identity, bool)
    # a window reads padded patches up to ceil((b + r) / m) away: an all-zero
    # neighbourhood (a depth layer's empty part) gives zero and is skipped
    reach = math.ceil((b + r) / m)
    nonzero = np.pad(padded.reshape(qh, m, qw, m, c_in).any(axis=(1, 3, 4)), reach)
    live = np.zeros((qh, qw), bool)
    for u in range(2 * reach + 1):
        for v in range(2 * reach + 1):
            live |= nonzero[u:u + qh, v:v + qw]
    # window of patch i: padded rows [i m - b, i m + m + b); its input reaches r further
    win = m + 2 * b
    lead = b + r
    ext = np.pad(padded, ((lead, lead + m), (lead, lead + m), (0, 0)))
    tw = blend_window(m, b).astype(np.float32)
    centre = np.arange(win) + 0.5 - b - m / 2.0
    first, last = centre < 0, centre >= 0
    # overlap-add grid: window origin i m - b sits in block i - a at offset a m - b
    a = math.ceil(b / m)
    e = a * m - b
    nb = math.ceil((e + win) / m)
    out = np.zeros((qh + nb, m, qw + nb, m, c), np.float32)

    def windows(ii, jj, hs):
        """Weighted results (n, win, win, C) of windows (ii, jj), kernels cropped to half-width hs
        (0 <= hs <= r; hs < 0: copy the input, an identity window)."""
        res = np.empty((len(ii), win, win, c), np.float32)
        o = r - max(hs, 0)                                  # crop offset inside the full input reach
        s_in = win + 2 * max(hs, 0)
        # a strided view of every window's input: gathering through it is ~10x
        # faster than fancy-indexing rows and columns
        blk = sliding_window_view(ext, (s_in, s_in), axis=(0, 1))[ii * m + o, jj * m + o]   # (n, C, s_in, s_in)
        if hs < 0:
            res[:] = np.moveaxis(blk[:, pr[:, 0]], 1, -1)
        else:
            f = fft.fast_size(s_in)
            kern = kernels[ip[ii], jp[jj]][:, k_used]                        # (n, C_k, k, k)
            crop = kern[:, :, r - hs:r + hs + 1, r - hs:r + hs + 1]
            if hs < r:                                                        # keep each channel's sum
                full_sum, crop_sum = kern.sum(axis=(-2, -1)), crop.sum(axis=(-2, -1))
                scale = np.where(crop_sum != 0, full_sum / np.where(crop_sum != 0, crop_sum, 1.0), 1.0)
                crop = crop * scale[..., None, None].astype(np.float32)
            spec_in, spec_k = fft.rfft2(blk[:, in_used], (f, f), be), fft.rfft2(crop, (f, f), be)
            if plain_pairs:
                spec = spec_in * spec_k
            else:
                spec = spec_in[:, in_of] * spec_k[:, k_of]
            full = fft.irfft2(spec, (f, f), be)
            # circular = linear convolution on the valid part [2 hs, 2 hs + win)
            res[:] = np.moveaxis(full[:, :, 2 * hs:2 * hs + win, 2 * hs:2 * hs + win], 1, -1)
        wy = np.where(ii[:, None] == 0, np.maximum(tw, first), tw)
        wy = np.where(ii[:, None] == qh - 1, np.maximum(wy, last), wy)
        wx = np.where(jj[:, None] == 0, np.maximum(tw, first), tw)
        wx = np.where(jj[:, None] == qw - 1, np.maximum(wx, last), wx)
        res *= (wy[:, :, None, None] * wx[:, None, :, None]).astype(np.float32)
        return ii, jj, res

    def add(ii, jj, res):
        grid = np.zeros((len(ii), nb * m, nb * m, c), np.float32)
        grid[:, e:e + win, e:e + win] = res
        grid = grid.reshape(len(ii), nb, m, nb, m, c)
        for u in range(nb):
            for v in range(nb):
                out[ii + u, :, jj + v] += grid[:, u, :, v]     # (ii, jj) unique within a chunk

    # group live windows by what they need: a copy, or an FFT of a given size
    # (the crop grows to fill that size: accuracy for free)
    support = kernel_support(kernels, support_eps, channels=k_used)
    need = np.where(ident[ip][:, jp], -1, support[ip][:, jp])
    size_of = np.array([fft.fast_size(win + 2 * s) for s in range(r + 1)])
    f_need = np.where(need >= 0, size_of[np.maximum(need, 0)], -1)
    jobs = [(live & (f_need == f_size), min(r, (int(f_size) - win) // 2))
            for f_size in np.unique(f_need[live & (need >= 0)])]
    if (live & (need < 0)).any():
        jobs.append((live & (need < 0), -1))
    pool = thread_pool()
    pending = []
    # two chunks in flight on the pool ahead of the (serial) overlap-add bounds the memory
    for sel, hs in jobs:
        ii_all, jj_all = np.nonzero(sel)
        size = max(16, int(chunk * (72.0 / (win + 2 * max(hs, 0))) ** 2))
        for start in range(0, len(ii_all), size):
            pending.append(pool.submit(windows, ii_all[start:start + size], jj_all[start:start + size], hs))
            if len(pending) > 2:
                add(*pending.pop(0).result())
    for fut in pending:
        add(*fut.result())
    full = out.reshape((qh + nb) * m, (qw + nb) * m, c)
    # padded row P is at full row P + a m (block i + u holds window offset u m - e)
    y0 = a * m + pp
    return np.ascontiguousarray(full[y0:y0 + h, a * m + pp:a * m + pp + w])
