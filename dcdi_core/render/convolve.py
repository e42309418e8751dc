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


METHODS = ("windows", "lowrank", "fast")
ACCELERATORS = ("torch",)


def blend_window(m: int, b: int) -> np.ndarray:
    """The 1-D weights (m + 2b,) of a patch over pixels [i m - b, (i + 1) m + b):
    1 inside, linear ramps 2b wide across each border, so that neighbouring
    windows sum to 1. b = m/2 is the tent (bilinear blend of patch results)."""
    x = np.arange(m + 2 * b) + 0.5 - b                  # pixel centre relative to the patch's first pixel
    rise = np.clip((x + b) / (2 * b), 0.0, 1.0)
    fall = np.clip((m + b - x) / (2 * b), 0.0, 1.0)
    return np.minimum(rise, fall)


def _live_windows(padded: np.ndarray, m: int, b: int, r: int) -> np.ndarray:
    """(qh, qw) bool: windows whose input (padded patches up to ceil((b + r) / m)
    away) is not all zero (a depth layer's empty part gives zero: skipped)."""
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    reach = math.ceil((b + r) / m)
    nonzero = np.pad(padded.reshape(qh, m, qw, m, -1).any(axis=(1, 3, 4)), reach)
    live = np.zeros((qh, qw), bool)
    for u in range(2 * reach + 1):
        for v in range(2 * reach + 1):
            live |= nonzero[u:u + qh, v:v + qw]
    return live


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
                   chunk: int = 384, fft_backend: str | None = None, method: str = "windows",
                   rank_eps: float = 2e-3, tile: int = 8, accelerator: str | None = None) -> np.ndarray:
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
    (float64), default the fastest installed (``fft.backend``).
    method: 'windows' (one FFT per patch window, the exact form) or
    'lowrank' (tiles of ``tile`` x ``tile`` patches, each tile's kernels
    replaced by their best rank-R approximation, R the smallest for which
    every kernel's L1 error is at most ``rank_eps`` of its L1 norm, so that
    each tile costs one FFT of its input and R of its eigen-PSFs instead of
    one per patch; the result differs from 'windows' by at most
    2 rank_eps max|image| (tested; see ``lowrank_convolve``); or 'fast'
    (the windows method laid out for speed, equal to 'windows' to float32
    rounding: ``convolve_fast.py``). accelerator: None (numpy) or 'torch'
    (the 'fast' method in torch, ``accel_torch.py``; needs torch, not in
    Blender). Returns float32 (H, W, len(pairs))."""
    img = np.asarray(image, dtype=np.float32)
    h, w, c_in = img.shape
    if m < 2 or m % 2:
        raise ValueError(f"patch size must be even and >= 2, got {m}")
    b = m // 2 if blend is None else int(blend)
    if not 1 <= b <= m // 2:
        raise ValueError(f"blend must be in [1, {m // 2}] px, got {blend}")
    if not 0.0 <= support_eps < 0.5:
        raise ValueError(f"support_eps must be in [0, 0.5), got {support_eps}")
    if method not in METHODS:
        raise ValueError(f"convolution method {method!r}: allowed {', '.join(METHODS)}")
    if method == "lowrank" and not (0.0 <= rank_eps < 0.5 and isinstance(tile, (int, np.integer)) and tile >= 1):
        raise ValueError(f"lowrank needs rank_eps in [0, 0.5) and tile >= 1 patches, got {rank_eps}, {tile}")
    if accelerator is not None and (accelerator not in ACCELERATORS or method != "fast"):
        raise ValueError(f"accelerator {accelerator!r}: allowed None or {', '.join(ACCELERATORS)}, with method "
                         f"'fast' (got method {method!r})")
    if accelerator == "torch":
        from . import accel_torch
        if not accel_torch.available():
            raise ValueError("accelerator 'torch' asked for, but torch cannot be imported here (Blender's Python "
                             "has none): leave it out for numpy")
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
    live = _live_windows(padded, m, b, r)
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

    support = kernel_support(kernels, support_eps, channels=k_used)
    if method == "fast":
        from . import convolve_fast as cf
        plan = cf.make_plan(img, kernels, m, ident, b, support, pr, pp, chunk)
        if accelerator == "torch":
            from .accel_torch import run_plan
            return run_plan(plan)
        return cf.run_numpy(plan, be)
    if method == "lowrank":
        out = _lowrank(ext, kernels, ident[ip][:, jp], live, support[ip][:, jp], ip, jp, m, b, r, tile, rank_eps,
                       pr, in_used, in_of, k_used, k_of, tw, be)
        return np.ascontiguousarray(out[b + pp:b + pp + h, b + pp:b + pp + w])
    # group live windows by what they need: a copy, or an FFT of a given size
    # (the crop grows to fill that size: accuracy for free)
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


def low_rank(a: np.ndarray, eps: float, max_rank: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """The best rank-R approximation coef @ basis of the rows of ``a`` (n, p)
    (truncated SVD, through the n x n Gram matrix), R the smallest for which
    every row's L1 error is at most ``eps`` times its L1 norm (eps = 0: the
    exact rank), searched up to ``max_rank``; beyond it the rows themselves
    (R = n, exact). Returns coef (n, R) and basis (R, p), float32."""
    a32 = np.asarray(a, np.float32)
    n = a32.shape[0]
    g = a32.astype(np.float64)
    lam, u = np.linalg.eigh(g @ g.T)
    lam, u = np.maximum(lam[::-1], 0.0), u[:, ::-1]
    l1 = np.abs(a32).sum(axis=1, dtype=np.float64)
    tol = eps * l1 * (1 + 1e-6) + 1e-30
    # L1 >= L2: ranks whose L2 residual (from the eigenvalues) already exceeds the tolerance cannot do
    res2 = (g ** 2).sum(axis=1)[:, None] - np.cumsum(u ** 2 * lam, axis=1)
    ok = (res2 <= tol[:, None] ** 2).all(axis=0)
    lo = int(np.argmax(ok)) + 1 if ok.any() else n
    hi = min(n, max_rank)
    if eps > 0 and lo <= hi:
        uu = u[:, :hi].astype(np.float32)
        basis = uu.T @ a32                                              # (hi, p)
        approx = uu[:, :lo] @ basis[:lo]
        for rank in range(lo, hi + 1):                                 # the first rank that does
            if rank > lo:
                approx += np.outer(uu[:, rank - 1], basis[rank - 1])
            if (np.abs(a32 - approx).sum(axis=1) <= tol).all():
                return uu[:, :rank].copy(), np.ascontiguousarray(basis[:rank])
    return np.eye(n, dtype=np.float32), a32.copy()                      # exact: every row its own


def _lowrank(ext, kernels, ident, live, support, ip, jp, m, b, r, tile, eps, pr, in_used, in_of, k_used, k_of,
             tw, be):
    """patch_convolve's 'lowrank' method on the padded frame (see there): the
    tent-blended sum over patches p of t_p (image * K_p) is, with each
    tile's kernels K_p ~ sum_r a_pr E_r, sum_r w_r (image * E_r) where
    w_r = sum_p t_p a_pr: one transform of the tile's input, and one
    product and inverse transform per eigen-PSF E_r and output channel.
    Each pixel is then rescaled by (sum_p t_p sum K_p) / (sum_p t_p sum
    K~_p), so a constant image stays constant. Identity patches are copied
    with their blend weights; patches whose neighbourhood is all zero are
    left out. Returns the blended frame (qh m + 2b, qw m + 2b, C), padded
    row P at row P + b."""
    from ..parallel import thread_pool

    qh, qw = live.shape
    c = len(pr)
    win = m + 2 * b
    centre = np.arange(win) + 0.5 - b - m / 2.0
    first, last = centre < 0, centre >= 0

    def wmat(i0, nt, q):
        """Blend weights (nt, nt m + 2b) of patches i0 .. i0 + nt - 1 over the tile's rows."""
        wm = np.zeros((nt, nt * m + 2 * b), np.float32)
        for u in range(nt):
            t = tw
            if i0 + u == 0:
                t = np.maximum(t, first)
            if i0 + u == q - 1:
                t = np.maximum(t, last)
            wm[u, u * m:u * m + win] = t
        return wm

    def work(i0, j0):
        nty, ntx = min(tile, qh - i0), min(tile, qw - j0)
        lv = live[i0:i0 + nty, j0:j0 + ntx]
        if not lv.any():
            return None
        idn = ident[i0:i0 + nty, j0:j0 + ntx] & lv
        blur = ~ident[i0:i0 + nty, j0:j0 + ntx] & lv
        wy, wx = wmat(i0, nty, qh), wmat(j0, ntx, qw)
        ly, lx = wy.shape[1], wx.shape[1]
        hs = int(support[i0:i0 + nty, j0:j0 + ntx][blur].max()) if blur.any() else 0
        o = r - hs
        inp = ext[i0 * m + o:i0 * m + o + ly + 2 * hs, j0 * m + o:j0 * m + o + lx + 2 * hs]
        res = np.zeros((ly, lx, c), np.float32)
        if idn.any():
            wid = wy.T @ idn.astype(np.float32) @ wx
            res += wid[..., None] * inp[hs:hs + ly, hs:hs + lx][:, :, pr[:, 0]]
        if not blur.any():
            return i0, j0, res
        fy, fx = fft.fast_size(ly + 2 * hs), fft.fast_size(lx + 2 * hs)
        spec_in = fft.rfft2(np.moveaxis(inp[..., in_used], -1, 0), (fy, fx), be)
        uu, vv = np.nonzero(blur)
        kern = kernels[ip[i0 + uu], jp[j0 + vv]][:, k_used]                  # (n, C_k, k, k)
        crop = kern[:, :, r - hs:r + hs + 1, r - hs:r + hs + 1]
        if hs < r:                                                           # keep each channel's sum
            full_sum, crop_sum = kern.sum(axis=(-2, -1)), crop.sum(axis=(-2, -1))
            scale = np.where(crop_sum != 0, full_sum / np.where(crop_sum != 0, crop_sum, 1.0), 1.0)
            crop = crop * scale[..., None, None].astype(np.float32)
        kk = 2 * hs + 1
        for kc in range(len(k_used)):
            a = crop[:, kc].reshape(len(uu), kk * kk)
            coef, basis = low_rank(a, eps)
            rank = len(basis)
            grid = np.zeros((nty, ntx, rank), np.float32)
            grid[uu, vv] = coef
            wr = wy.T @ grid.transpose(2, 0, 1) @ wx                     # (R, ly, lx)
            sums = np.zeros((nty, ntx), np.float32)
            sums[uu, vv] = a.sum(axis=1)
            want = wy.T @ sums @ wx
            got = wy.T @ (grid @ basis.sum(axis=1)) @ wx                  # sum_r w_r sum E_r, at the patches
            fix = np.where(np.abs(got) > 1e-12, want / np.where(np.abs(got) > 1e-12, got, 1.0), 1.0)
            spec_k = fft.rfft2(basis.reshape(rank, kk, kk), (fy, fx), be)
            for q in np.flatnonzero(k_of == kc):
                conv = fft.irfft2(spec_in[in_of[q]][None] * spec_k, (fy, fx), be)
                acc = wr[0] * conv[0, 2 * hs:2 * hs + ly, 2 * hs:2 * hs + lx]
                for t in range(1, rank):
                    acc += wr[t] * conv[t, 2 * hs:2 * hs + ly, 2 * hs:2 * hs + lx]
                res[..., q] += acc * fix
        return i0, j0, res

    out = np.zeros((qh * m + 2 * b, qw * m + 2 * b, c), np.float32)
    tiles = [(i0, j0) for i0 in range(0, qh, tile) for j0 in range(0, qw, tile)]
    for got in thread_pool().map(lambda t: work(*t), tiles):
        if got is not None:
            i0, j0, res = got
            out[i0 * m:i0 * m + res.shape[0], j0 * m:j0 * m + res.shape[1]] += res
    return out
