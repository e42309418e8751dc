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

from ..optics.trace import thread_pool


def blend_window(m: int, b: int) -> np.ndarray:
    """The 1-D weights (m + 2b,) of a patch over pixels [i m - b, (i + 1) m + b):
    1 inside, linear ramps 2b wide across each border, so that neighbouring
    windows sum to 1. b = m/2 is the tent (bilinear blend of patch results)."""
    x = np.arange(m + 2 * b) + 0.5 - b                  # pixel centre relative to the patch's first pixel
    rise = np.clip((x + b) / (2 * b), 0.0, 1.0)
    fall = np.clip((m + b - x) / (2 * b), 0.0, 1.0)
    return np.minimum(rise, fall)


def _fft_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (sizes pocketfft handles fastest)."""
    best = 1 << (n - 1).bit_length()
    for b in range(8):
        for c in range(6):
            v = 3 ** b * 5 ** c
            while v < n:
                v *= 2
            best = min(best, v)
    return best


def patch_convolve(image: np.ndarray, kernels: np.ndarray, m: int, *, identity: np.ndarray | None = None,
                   blend: int | None = None, chunk: int = 384) -> np.ndarray:
    """Convolve ``image`` (H, W, C) with one kernel per m x m patch.

    kernels: (nph, npw, C, k, k) with nph = ceil(H / m), npw = ceil(W / m),
    k odd, centred on (k // 2, k // 2), rows along image rows. identity:
    optional (nph, npw) bool, patches to copy. blend: half-width b (px) of
    the ramps between neighbouring patches' results (default m / 2, the
    tent); smaller is faster (windows m + 2b) and blends over 2b pixels.
    Returns float32 (H, W, C)."""
    img = np.asarray(image, dtype=np.float32)
    h, w, c = img.shape
    if m < 2 or m % 2:
        raise ValueError(f"patch size must be even and >= 2, got {m}")
    b = m // 2 if blend is None else int(blend)
    if not 1 <= b <= m // 2:
        raise ValueError(f"blend must be in [1, {m // 2}] px, got {blend}")
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    k = kernels.shape[-1]
    if kernels.shape[:3] != (nph, npw, c) or kernels.shape[-2] != k or k % 2 == 0:
        raise ValueError(f"kernels must be ({nph}, {npw}, {c}, k, k) with k odd; got {kernels.shape}")
    r = k // 2
    # pad by whole patches (>= r) so that padded patches line up with the image's
    pp = m * math.ceil(r / m)
    mode = "reflect" if min(h, w) > 1 else "edge"
    padded = np.pad(img, ((pp, pp + nph * m - h), (pp, pp + npw * m - w), (0, 0)), mode=mode)
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    ip = np.clip(np.arange(qh) - pp // m, 0, nph - 1)
    jp = np.clip(np.arange(qw) - pp // m, 0, npw - 1)
    kern = kernels[ip][:, jp]
    ident = None if identity is None else np.asarray(identity)[ip][:, jp]
    # window of patch i: padded rows [i m - b, i m + m + b); its input reaches r further
    win = m + 2 * b
    lead = b + r
    ext = np.pad(padded, ((lead, lead + m), (lead, lead + m), (0, 0)))
    s_in = win + 2 * r
    f = _fft_size(s_in)
    rows_in = np.arange(qh)[:, None] * m + np.arange(s_in)[None, :]     # ext row = padded row + lead
    cols_in = np.arange(qw)[:, None] * m + np.arange(s_in)[None, :]
    tw = blend_window(m, b).astype(np.float32)
    centre = np.arange(win) + 0.5 - b - m / 2.0
    first, last = centre < 0, centre >= 0
    # overlap-add grid: window origin i m - b sits in block i - a at offset a m - b
    a = math.ceil(b / m)
    e = a * m - b
    nb = math.ceil((e + win) / m)
    out = np.zeros((qh + nb, m, qw + nb, m, c), np.float32)
    flat = [(i, j) for i in range(qh) for j in range(qw)]

    def windows(sel):
        """Weighted results (n, 2m, 2m, C) of the patches in ``sel``."""
        ii = np.array([p[0] for p in sel])
        jj = np.array([p[1] for p in sel])
        blk = ext[rows_in[ii][:, :, None], cols_in[jj][:, None, :]]       # (n, s_in, s_in, C)
        res = np.zeros((len(sel), win, win, c), np.float32)
        live = blk.reshape(len(sel), -1).any(axis=1)                      # an all-zero input stays zero
        copy = live & (np.zeros(len(sel), bool) if ident is None else ident[ii, jj])
        conv = live & ~copy
        if conv.any():
            bt = np.moveaxis(blk[conv], -1, 1)                             # (n', C, s_in, s_in)
            spec = np.fft.rfft2(bt, s=(f, f)) * np.fft.rfft2(kern[ii[conv], jj[conv]], s=(f, f))
            full = np.fft.irfft2(spec, s=(f, f))
            # circular = linear convolution on the valid part [2r, 2r + win)
            res[conv] = np.moveaxis(full[:, :, 2 * r:2 * r + win, 2 * r:2 * r + win], 1, -1)
        if copy.any():
            res[copy] = blk[copy][:, r:r + win, r:r + win]
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

    # two chunks in flight on the pool ahead of the (serial) overlap-add bounds the memory
    pool = thread_pool()
    pending = []
    for start in range(0, len(flat), chunk):
        pending.append(pool.submit(windows, flat[start:start + chunk]))
        if len(pending) > 2:
            add(*pending.pop(0).result())
    for fut in pending:
        add(*fut.result())
    full = out.reshape((qh + nb) * m, (qw + nb) * m, c)
    # padded row P is at full row P + a m (block i + u holds window offset u m - e)
    y0 = a * m + pp
    return np.ascontiguousarray(full[y0:y0 + h, a * m + pp:a * m + pp + w])
