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
the FFTs run on the thread pool. How the result is computed (method, blend,
crop tolerance, FFT backend, ...) is one :class:`ConvolveOptions`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..errors import InputRangeError
from ..parallel import thread_pool
from . import fft
from .windows import blend_window, live_windows


METHODS = ("windows", "lowrank", "fast")
ACCELERATORS = ("torch",)


def _is_int(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, np.integer))


def _is_real(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float, np.integer, np.floating))


@dataclass(frozen=True)
class ConvolveOptions:
    """How :func:`patch_convolve` computes its result (checked on creation).

    method: 'windows' (one FFT per patch window, the exact form), 'lowrank'
    (tiles of ``tile`` x ``tile`` patches, each tile's kernels replaced by
    their best rank-R approximation, R the smallest for which every kernel's
    L1 error is at most ``rank_eps`` of its L1 norm, so that each tile costs
    one FFT of its input and R of its eigen-PSFs instead of one per patch;
    the result differs from 'windows' by at most 2 rank_eps max|image|,
    tested) or 'fast' (the windows method laid out for speed, equal to
    'windows' to float32 rounding: ``convolve_fast.py``).
    blend: half-width b (px) of the ramps between neighbouring patches'
    results, 1 <= b <= m / 2 (None: m / 2, the tent); smaller is faster
    (windows m + 2b) and blends over 2b pixels.
    support_eps: each kernel is cropped to the centred square that holds all
    but this fraction of every channel's energy, in [0, 0.5) (then rescaled
    to its former sum, so a constant image stays constant), and windows are
    grouped by the FFT size their crop needs; 0 crops only exact zeros (see
    ``python -m lab report simulation-accuracy`` for error against time).
    rank_eps, tile: the 'lowrank' tolerance, in [0, 0.5), and its tile side
    in patches (>= 1).
    fft_backend: 'scipy' (float32) or 'numpy' (float64); None: the fastest
    installed (``fft.backend``).
    accelerator: None (numpy) or 'torch' (the 'fast' method in torch,
    ``accel_torch.py``; needs torch, which Blender's Python lacks).
    chunk: windows per batch of FFTs (at a 72 px window; scaled by the
    window's area), >= 1: it bounds the memory, not the result.
    """

    method: str = "windows"
    blend: int | None = None
    support_eps: float = 1e-3
    rank_eps: float = 2e-3
    tile: int = 8
    fft_backend: str | None = None
    accelerator: str | None = None
    chunk: int = 384

    def __post_init__(self):
        if self.method not in METHODS:
            raise InputRangeError("convolution method", self.method, ", ".join(METHODS))
        if self.blend is not None and not (_is_int(self.blend) and self.blend >= 1):
            raise InputRangeError("blend", self.blend, "an integer >= 1 px (at most half the patch), or None "
                                  "for half the patch")
        for name in ("support_eps", "rank_eps"):
            value = getattr(self, name)
            if not (_is_real(value) and 0.0 <= value < 0.5):
                raise InputRangeError(name, value, "a fraction in [0, 0.5)")
        for name in ("tile", "chunk"):
            value = getattr(self, name)
            if not (_is_int(value) and value >= 1):
                raise InputRangeError(name, value, "an integer >= 1")
        fft.backend(self.fft_backend)              # its own message: the backends this Python has
        self._check_accelerator()

    def _check_accelerator(self) -> None:
        if self.accelerator is None:
            return
        if self.accelerator not in ACCELERATORS or self.method != "fast":
            raise InputRangeError("accelerator", self.accelerator, f"None (numpy) or {', '.join(ACCELERATORS)}, "
                                  f"with method 'fast' (got method {self.method!r})")
        from . import accel_torch
        if not accel_torch.available():
            raise InputRangeError("accelerator", self.accelerator, "None here: torch cannot be imported (Blender's "
                                  "Python has none)")

    def blend_px(self, m: int) -> int:
        """The ramps' half-width b (px) for m-px patches: ``blend``, or m / 2."""
        if self.blend is None:
            return m // 2
        if self.blend > m // 2:
            raise InputRangeError("blend", self.blend, f"an integer in [1, {m // 2}] px (half the patch), or None")
        return int(self.blend)


def box_reach(kernel_size: int, m: int) -> int:
    """px around a group of m-px patches that its blur with
    ``kernel_size``-px kernels reaches: the kernel's radius plus a patch
    (more than the m / 2 a blend window reaches past its patch), rounded up
    to whole patches. Outside the group's box grown by it the blur is zero,
    so a group (a bokeh layer, a multires level) is blurred on that box alone."""
    return m * math.ceil((kernel_size // 2 + m) / m)


def patch_box(mask: np.ndarray, m: int, grow: int) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s (H, W) bounding box grown by ``grow`` px
    and aligned to the m-px patch grid (so its patches are the image's)."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    y0, x0 = max(0, (rows[0] - grow) // m * m), max(0, (cols[0] - grow) // m * m)
    y1, x1 = min(h, -(-(rows[-1] + 1 + grow) // m) * m), min(w, -(-(cols[-1] + 1 + grow) // m) * m)
    return slice(int(y0), int(y1)), slice(int(x0), int(x1))


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


def patch_convolve(image: np.ndarray, kernels: np.ndarray, m: int, options: ConvolveOptions = ConvolveOptions(),
                   *, identity: np.ndarray | None = None, pairs=None) -> np.ndarray:
    """Convolve ``image`` (H, W, C) with one kernel per m x m patch (m px, even).

    kernels: (nph, npw, C, k, k) with nph = ceil(H / m), npw = ceil(W / m),
    k odd, centred on (k // 2, k // 2), rows along image rows. options: how
    the result is computed (:class:`ConvolveOptions`; the default is the
    exact 'windows' method). identity: optional (nph, npw) bool, patches to
    copy. pairs: the output channels as (image channel, kernel channel)
    pairs (default: channel c of the image with kernel channel c); each
    distinct image and kernel channel is transformed once (the bokeh blurs
    one coverage channel with the three colour PSFs this way).
    Returns float32 (H, W, len(pairs))."""
    from ..parallel import one_blas_thread
    with one_blas_thread():
        return _patch_convolve(image, kernels, m, options, identity, pairs)


def _patch_convolve(image, kernels, m, options, identity, pairs) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    b, pr = _check_call(img, kernels, m, options, pairs)
    h, w = img.shape[:2]
    ident = np.zeros((math.ceil(h / m), math.ceil(w / m)), bool) if identity is None else np.asarray(identity, bool)
    # an identity patch is copied: its kernel's support is never read
    support = np.zeros(ident.shape, np.int64)
    if (~ident).any():
        support[~ident] = kernel_support(kernels[~ident], options.support_eps, channels=np.unique(pr[:, 1]))
    if options.method == "fast":
        return _fast_method(img, kernels, m, b, ident, support, pr, options)
    fr = _frame(img, kernels, m, b, pr, ident, support, fft.backend(options.fft_backend))
    if options.method == "lowrank":
        out = _lowrank(fr, kernels, options.tile, options.rank_eps)
        return np.ascontiguousarray(out[b + fr.pp:b + fr.pp + h, b + fr.pp:b + fr.pp + w])
    return _windows_method(fr, kernels, options.chunk)


def _check_call(img: np.ndarray, kernels: np.ndarray, m: int, options: ConvolveOptions, pairs):
    """The blend half-width b and the (image channel, kernel channel) pairs
    (n, 2), once the patch size, kernels and pairs are checked against the image."""
    h, w, c_in = img.shape
    if not isinstance(options, ConvolveOptions):
        raise InputRangeError("options", options, "ConvolveOptions (how the convolution is computed)")
    if not _is_int(m) or m < 2 or m % 2:
        raise InputRangeError("patch size", m, "an even number of pixels >= 2")
    b = options.blend_px(m)
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    k = kernels.shape[-1]
    pr = np.array([(i, i) for i in range(c_in)] if pairs is None else pairs, int).reshape(-1, 2)
    kc = kernels.shape[2] if kernels.ndim == 5 else -1
    if (kernels.shape[:2] != (nph, npw) or kernels.shape[-2] != k or k % 2 == 0 or len(pr) == 0
            or not ((0 <= pr) & (pr < [c_in, kc])).all()):
        raise InputRangeError("kernels and pairs", (kernels.shape, pairs),
                              f"kernels ({nph}, {npw}, C, k, k) with k odd, and pairs (image channel, kernel "
                              f"channel) within the image's {c_in} and the kernels' channels")
    return b, pr


def _padding(m: int, kernels: np.ndarray) -> int:
    """Pixels of padding around the image: whole patches (>= the kernels'
    radius), so that padded patches line up with the image's."""
    return m * math.ceil((kernels.shape[-1] // 2) / m)


def _fast_method(img, kernels, m, b, ident, support, pr, options: ConvolveOptions) -> np.ndarray:
    """The 'fast' method (``convolve_fast.py``): numpy, or torch with accelerator 'torch'."""
    from . import convolve_fast as cf
    plan = cf.make_plan(img, kernels, m, ident, b, support, pr, _padding(m, kernels), options.chunk)
    if options.accelerator == "torch":
        from .accel_torch import run_plan
        return run_plan(plan)
    return cf.run_numpy(plan, fft.backend(options.fft_backend))


@dataclass
class _Frame:
    """The padded frame the 'windows' and 'lowrank' methods work on: the
    image padded by ``pp`` px (whole patches), its windows on a (qh, qw) grid
    of padded patches, and the channel bookkeeping."""

    m: int                     # patch size (px)
    b: int                     # blend half-width (px)
    r: int                     # kernel radius (px)
    pp: int                    # padding (px) on each side of the image
    h: int                     # the image's rows
    w: int                     # the image's columns
    ext: np.ndarray            # the padded image with every window's input reach: padded row P at P + b + r
    live: np.ndarray           # (qh, qw) bool: windows whose neighbourhood is not all zero
    ip: np.ndarray             # (qh,) patch row of each padded patch row (the nearest for padding)
    jp: np.ndarray             # (qw,)
    ident: np.ndarray          # (qh, qw) bool: windows copied
    support: np.ndarray        # (qh, qw) int: the kernels' half-width (px) within support_eps
    pr: np.ndarray             # (c, 2) (image channel, kernel channel) pairs
    in_used: np.ndarray        # the image channels read, and each pair's index into them
    in_of: np.ndarray
    k_used: np.ndarray         # the kernel channels read, and each pair's index into them
    k_of: np.ndarray
    plain_pairs: bool          # pair n is (n, n) among the used channels: no reindexing
    tw: np.ndarray             # (win,) float32 blend weights of a window
    first: np.ndarray          # (win,) bool: a window's pixels before the patch centre
    last: np.ndarray           # (win,) bool: and from it on
    be: str                    # FFT backend

    @property
    def win(self) -> int:
        return self.m + 2 * self.b

    @property
    def qh(self) -> int:
        return len(self.ip)

    @property
    def qw(self) -> int:
        return len(self.jp)

    @property
    def c(self) -> int:
        return len(self.pr)


def _frame(img, kernels, m: int, b: int, pr, ident, support, be: str) -> _Frame:
    h, w = img.shape[:2]
    nph, npw = ident.shape
    r = kernels.shape[-1] // 2
    pp = _padding(m, kernels)
    mode = "reflect" if min(h, w) > 1 else "edge"
    padded = np.pad(img, ((pp, pp + nph * m - h), (pp, pp + npw * m - w), (0, 0)), mode=mode)
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    ip = np.clip(np.arange(qh) - pp // m, 0, nph - 1)         # padding patches take their nearest patch's kernel
    jp = np.clip(np.arange(qw) - pp // m, 0, npw - 1)
    # a window reads padded patches up to ceil((b + r) / m) away: an all-zero
    # neighbourhood (a depth layer's empty part) gives zero and is skipped
    live = live_windows(padded, m, b, r)
    # window of patch i: padded rows [i m - b, i m + m + b); its input reaches r further
    lead = b + r
    ext = np.pad(padded, ((lead, lead + m), (lead, lead + m), (0, 0)))
    in_used, in_of = np.unique(pr[:, 0], return_inverse=True)        # transform each input channel once
    k_used, k_of = np.unique(pr[:, 1], return_inverse=True)          # and each kernel channel once
    c = len(pr)
    plain_pairs = (np.array_equal(in_of, np.arange(c)) and np.array_equal(k_of, np.arange(c)))
    centre = np.arange(m + 2 * b) + 0.5 - b - m / 2.0
    return _Frame(m, b, r, pp, h, w, ext, live, ip, jp, ident[ip][:, jp], support[ip][:, jp], pr, in_used, in_of,
                  k_used, k_of, plain_pairs, blend_window(m, b).astype(np.float32), centre < 0, centre >= 0, be)


def _edge_weights(fr: _Frame, idx: np.ndarray, q: int) -> np.ndarray:
    """(n, win) blend weights of windows ``idx`` along an axis of q windows:
    the tent, held at 1 on the outer half of the first and last windows
    (nothing beyond them adds up to 1 there)."""
    t = np.where(idx[:, None] == 0, np.maximum(fr.tw, fr.first), fr.tw)
    return np.where(idx[:, None] == q - 1, np.maximum(t, fr.last), t)


def _crop_kernels(kern: np.ndarray, r: int, hs: int) -> np.ndarray:
    """Kernels (n, C, 2r + 1, 2r + 1) cropped to the centred (2 hs + 1)^2
    square, each channel rescaled to its full sum (a constant image stays
    constant)."""
    crop = kern[:, :, r - hs:r + hs + 1, r - hs:r + hs + 1]
    if hs < r:
        full_sum, crop_sum = kern.sum(axis=(-2, -1)), crop.sum(axis=(-2, -1))
        scale = np.where(crop_sum != 0, full_sum / np.where(crop_sum != 0, crop_sum, 1.0), 1.0)
        crop = crop * scale[..., None, None].astype(np.float32)
    return crop


# ------------------------------------------------------------------ 'windows'
def _windows_method(fr: _Frame, kernels: np.ndarray, chunk: int) -> np.ndarray:
    """The 'windows' method: each live window convolved by FFT (or copied) on
    the thread pool, weighted and added up; returns the image's frame."""
    acc = _Accumulator(fr)
    pool = thread_pool()
    pending = []
    # two chunks in flight on the pool ahead of the (serial) overlap-add bounds the memory
    for ii, jj, hs in _window_chunks(fr, chunk):
        pending.append(pool.submit(_window_results, fr, kernels, ii, jj, hs))
        if len(pending) > 2:
            acc.add(*pending.pop(0).result())
    for fut in pending:
        acc.add(*fut.result())
    return acc.image()


def _window_groups(fr: _Frame) -> list[tuple[np.ndarray, int]]:
    """The live windows grouped by what they need: (selection (qh, qw) bool,
    crop half-width hs) per FFT size, the crop grown to fill that size
    (accuracy for free), and the copies last (hs = -1)."""
    need = np.where(fr.ident, -1, fr.support)
    size_of = np.array([fft.fast_size(fr.win + 2 * s) for s in range(fr.r + 1)])
    f_need = np.where(need >= 0, size_of[np.maximum(need, 0)], -1)
    groups = [(fr.live & (f_need == f_size), min(fr.r, (int(f_size) - fr.win) // 2))
              for f_size in np.unique(f_need[fr.live & (need >= 0)])]
    if (fr.live & (need < 0)).any():
        groups.append((fr.live & (need < 0), -1))
    return groups


def _window_chunks(fr: _Frame, chunk: int):
    """(ii, jj, hs) batches of windows, ``chunk`` of them at a 72 px input
    (fewer for larger inputs)."""
    for sel, hs in _window_groups(fr):
        ii_all, jj_all = np.nonzero(sel)
        size = max(16, int(chunk * (72.0 / (fr.win + 2 * max(hs, 0))) ** 2))
        for start in range(0, len(ii_all), size):
            yield ii_all[start:start + size], jj_all[start:start + size], hs


def _window_results(fr: _Frame, kernels: np.ndarray, ii: np.ndarray, jj: np.ndarray, hs: int):
    """(ii, jj, weighted results (n, win, win, C)) of windows (ii, jj), their
    kernels cropped to half-width hs (0 <= hs <= r; hs < 0: copies)."""
    win = fr.win
    o = fr.r - max(hs, 0)                                 # crop offset inside the full input reach
    s_in = win + 2 * max(hs, 0)
    # a strided view of every window's input: gathering through it is ~10x
    # faster than fancy-indexing rows and columns
    blk = sliding_window_view(fr.ext, (s_in, s_in), axis=(0, 1))[ii * fr.m + o, jj * fr.m + o]   # (n, C, s_in, s_in)
    res = np.empty((len(ii), win, win, fr.c), np.float32)
    if hs < 0:
        res[:] = np.moveaxis(blk[:, fr.pr[:, 0]], 1, -1)
    else:
        res[:] = _window_convolutions(fr, kernels, blk, ii, jj, hs)
    wy, wx = _edge_weights(fr, ii, fr.qh), _edge_weights(fr, jj, fr.qw)
    res *= (wy[:, :, None, None] * wx[:, None, :, None]).astype(np.float32)
    return ii, jj, res


def _window_convolutions(fr: _Frame, kernels, blk, ii, jj, hs: int) -> np.ndarray:
    """The windows' inputs ``blk`` (n, C_in, s, s) convolved with their
    kernels cropped to half-width hs: (n, win, win, C)."""
    win = fr.win
    f = fft.fast_size(blk.shape[-1])
    crop = _crop_kernels(kernels[fr.ip[ii], fr.jp[jj]][:, fr.k_used], fr.r, hs)       # (n, C_k, 2hs+1, 2hs+1)
    spec_in, spec_k = fft.rfft2(blk[:, fr.in_used], (f, f), fr.be), fft.rfft2(crop, (f, f), fr.be)
    if fr.plain_pairs:
        spec = spec_in * spec_k
    else:
        spec = spec_in[:, fr.in_of] * spec_k[:, fr.k_of]
    full = fft.irfft2(spec, (f, f), fr.be)
    # circular = linear convolution on the valid part [2 hs, 2 hs + win)
    return np.moveaxis(full[:, :, 2 * hs:2 * hs + win, 2 * hs:2 * hs + win], 1, -1)


class _Accumulator:
    """The overlap-add of weighted windows: the origin i m - b of window i
    sits in block i - a at offset e = a m - b, and each window spans nb
    blocks of m px."""

    def __init__(self, fr: _Frame):
        self.fr = fr
        self.a = math.ceil(fr.b / fr.m)
        self.e = self.a * fr.m - fr.b
        self.nb = math.ceil((self.e + fr.win) / fr.m)
        self.out = np.zeros((fr.qh + self.nb, fr.m, fr.qw + self.nb, fr.m, fr.c), np.float32)

    def add(self, ii: np.ndarray, jj: np.ndarray, res: np.ndarray) -> None:
        m, e, nb, win = self.fr.m, self.e, self.nb, self.fr.win
        grid = np.zeros((len(ii), nb * m, nb * m, self.fr.c), np.float32)
        grid[:, e:e + win, e:e + win] = res
        grid = grid.reshape(len(ii), nb, m, nb, m, self.fr.c)
        for u in range(nb):
            for v in range(nb):
                self.out[ii + u, :, jj + v] += grid[:, u, :, v]     # (ii, jj) unique within a chunk

    def image(self) -> np.ndarray:
        """The image's frame (h, w, C) out of the sum."""
        fr = self.fr
        full = self.out.reshape((fr.qh + self.nb) * fr.m, (fr.qw + self.nb) * fr.m, fr.c)
        # padded row P is at full row P + a m (block i + u holds window offset u m - e)
        o = self.a * fr.m + fr.pp
        return np.ascontiguousarray(full[o:o + fr.h, o:o + fr.w])


# ------------------------------------------------------------------ 'lowrank'
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


def _lowrank(fr: _Frame, kernels: np.ndarray, tile: int, eps: float) -> np.ndarray:
    """The 'lowrank' method on the padded frame (``ConvolveOptions``): the
    tent-blended sum over patches p of t_p (image * K_p) is, with each
    tile's kernels K_p ~ sum_r a_pr E_r, sum_r w_r (image * E_r) where
    w_r = sum_p t_p a_pr: one transform of the tile's input, and one
    product and inverse transform per eigen-PSF E_r and output channel.
    Each pixel is then rescaled by (sum_p t_p sum K_p) / (sum_p t_p sum
    K~_p), so a constant image stays constant. Identity patches are copied
    with their blend weights; patches whose neighbourhood is all zero are
    left out. Returns the blended frame (qh m + 2b, qw m + 2b, C), padded
    row P at row P + b."""
    out = np.zeros((fr.qh * fr.m + 2 * fr.b, fr.qw * fr.m + 2 * fr.b, fr.c), np.float32)
    tiles = [(i0, j0) for i0 in range(0, fr.qh, tile) for j0 in range(0, fr.qw, tile)]
    for got in thread_pool().map(lambda t: _lowrank_tile(fr, kernels, tile, eps, *t), tiles):
        if got is not None:
            i0, j0, res = got
            out[i0 * fr.m:i0 * fr.m + res.shape[0], j0 * fr.m:j0 * fr.m + res.shape[1]] += res
    return out


@dataclass
class _Tile:
    """A tile of patches of the 'lowrank' method, as its blur needs it."""

    i0: int                    # its first patch row and column on the padded grid
    j0: int
    wy: np.ndarray             # (nty, ly) blend weights of its patch rows over its pixel rows
    wx: np.ndarray             # (ntx, lx)
    blur: np.ndarray           # (nty, ntx) bool: patches blurred
    hs: int                    # the kernels' crop half-width (px): the widest support among them
    inp: np.ndarray            # (ly + 2 hs, lx + 2 hs, C_in) its input


def _lowrank_tile(fr: _Frame, kernels: np.ndarray, tile: int, eps: float, i0: int, j0: int):
    """(i0, j0, blended result (ly, lx, C)) of the tile whose first patch is
    (i0, j0), or None where its neighbourhood is all zero."""
    nty, ntx = min(tile, fr.qh - i0), min(tile, fr.qw - j0)
    lv = fr.live[i0:i0 + nty, j0:j0 + ntx]
    if not lv.any():
        return None
    ident = fr.ident[i0:i0 + nty, j0:j0 + ntx]
    copy, blur = ident & lv, ~ident & lv
    wy, wx = _tile_weights(fr, i0, nty, fr.qh), _tile_weights(fr, j0, ntx, fr.qw)
    ly, lx = wy.shape[1], wx.shape[1]
    hs = int(fr.support[i0:i0 + nty, j0:j0 + ntx][blur].max()) if blur.any() else 0
    o = fr.r - hs
    inp = fr.ext[i0 * fr.m + o:i0 * fr.m + o + ly + 2 * hs, j0 * fr.m + o:j0 * fr.m + o + lx + 2 * hs]
    res = np.zeros((ly, lx, fr.c), np.float32)
    if copy.any():
        wid = wy.T @ copy.astype(np.float32) @ wx
        res += wid[..., None] * inp[hs:hs + ly, hs:hs + lx][:, :, fr.pr[:, 0]]
    if blur.any():
        _add_eigen_blur(res, fr, kernels, eps, _Tile(i0, j0, wy, wx, blur, hs, inp))
    return i0, j0, res


def _tile_weights(fr: _Frame, i0: int, nt: int, q: int) -> np.ndarray:
    """Blend weights (nt, nt m + 2b) of patches i0 .. i0 + nt - 1 (of q) over the tile's rows."""
    rows = _edge_weights(fr, np.arange(i0, i0 + nt), q)
    wm = np.zeros((nt, nt * fr.m + 2 * fr.b), np.float32)
    for u in range(nt):
        wm[u, u * fr.m:u * fr.m + fr.win] = rows[u]
    return wm


def _add_eigen_blur(res: np.ndarray, fr: _Frame, kernels: np.ndarray, eps: float, t: _Tile) -> None:
    """Adds to ``res`` the tile's blurred patches: per kernel channel, the
    eigen-PSFs of the patches' cropped kernels convolved with the input,
    weighted by their blended coefficients, rescaled to keep each pixel's sum."""
    ly, lx, hs = t.wy.shape[1], t.wx.shape[1], t.hs
    fy, fx = fft.fast_size(ly + 2 * hs), fft.fast_size(lx + 2 * hs)
    spec_in = fft.rfft2(np.moveaxis(t.inp[..., fr.in_used], -1, 0), (fy, fx), fr.be)
    uu, vv = np.nonzero(t.blur)
    crop = _crop_kernels(kernels[fr.ip[t.i0 + uu], fr.jp[t.j0 + vv]][:, fr.k_used], fr.r, hs)
    kk = 2 * hs + 1
    for kc in range(len(fr.k_used)):
        basis, wr, fix = _eigen_psfs(crop[:, kc].reshape(len(uu), kk * kk), eps, t, uu, vv)
        spec_k = fft.rfft2(basis.reshape(len(basis), kk, kk), (fy, fx), fr.be)
        for q in np.flatnonzero(fr.k_of == kc):
            conv = fft.irfft2(spec_in[fr.in_of[q]][None] * spec_k, (fy, fx), fr.be)
            acc = wr[0] * conv[0, 2 * hs:2 * hs + ly, 2 * hs:2 * hs + lx]
            for e in range(1, len(basis)):
                acc += wr[e] * conv[e, 2 * hs:2 * hs + ly, 2 * hs:2 * hs + lx]
            res[..., q] += acc * fix


def _eigen_psfs(a: np.ndarray, eps: float, t: _Tile, uu: np.ndarray, vv: np.ndarray):
    """The tile's kernels ``a`` (n, kk^2) of one channel, at patches (uu,
    vv): (eigen-PSFs (R, kk^2), their blended weights (R, ly, lx), the
    per-pixel fix (ly, lx) that keeps sum_p t_p sum K_p)."""
    nty, ntx = t.blur.shape
    coef, basis = low_rank(a, eps)
    grid = np.zeros((nty, ntx, len(basis)), np.float32)
    grid[uu, vv] = coef
    wr = t.wy.T @ grid.transpose(2, 0, 1) @ t.wx                    # (R, ly, lx)
    sums = np.zeros((nty, ntx), np.float32)
    sums[uu, vv] = a.sum(axis=1)
    want = t.wy.T @ sums @ t.wx
    got = t.wy.T @ (grid @ basis.sum(axis=1)) @ t.wx                # sum_r w_r sum E_r, at the patches
    fix = np.where(np.abs(got) > 1e-12, want / np.where(np.abs(got) > 1e-12, got, 1.0), 1.0)
    return basis, wr, fix
