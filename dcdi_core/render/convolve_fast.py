"""``ConvolveOptions(method="fast")``: the windows method restructured, same result.

The maths is that of the default ``windows`` method (convolve.py): every
patch's window of m + 2b pixels, its input reaching the kernel's half-width
further, convolved by FFT with the patch's kernel cropped to its support
and rescaled to its sum, weighted by the tent, added up. What changes is
only how the work is laid out (measured in ``dcdi bench render``):

- windows that never reach the returned frame are not computed (the outer
  ring of padding patches), and the border windows' special weights, which
  only touch that ring, are not applied;
- the kernel crop is copied straight from the kernel array (no copy of the
  full 41 x 41 kernels first) and rescaled by precomputed sums;
- the kernel's forward transform skips its rows of zeros (a transform along
  the kernel's rows first, then along the columns), and the inverse keeps
  only the ``win`` rows that are used before its last stage (``fft.py``);
- the tent weights are one (win, win) array, multiplied in place;
- the overlap-add is one indexed add per parity class of windows: windows
  two patches apart never overlap (win <= 2m), so each class is added
  through a strided view of the output without a scratch grid.

The result equals ``windows`` to float32 rounding (tested, and in
``python -m lab report simulation-accuracy``). ``accel_torch.py`` runs the same plan
in torch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided, sliding_window_view

from . import fft
from .windows import blend_window, live_windows


@dataclass
class Plan:
    """Everything the fast windows method needs, backend-free (numpy arrays)."""

    ext: np.ndarray            # (H', W', C_in) the padded input with the windows' reach
    kernels: np.ndarray        # (nph, npw, C_k, k, k) as given
    ksum: np.ndarray           # (nph, npw, C_k) each kernel channel's sum
    ip: np.ndarray             # (qh,) patch row of each padded window row
    jp: np.ndarray             # (qw,)
    m: int
    b: int
    r: int
    win: int
    pr: np.ndarray             # (c, 2) (image channel, kernel channel) pairs
    in_used: np.ndarray
    in_of: np.ndarray
    k_used: np.ndarray
    k_of: np.ndarray
    plain_pairs: bool
    weight: np.ndarray         # (win, win) float32 tent product
    jobs: list                 # [(ii, jj, hs)] per FFT size; hs < 0: identity copy
    acc_shape: tuple           # (c, rows, cols) of the accumulator, origin at padded (-b, -b)
    grid: tuple                # (qh, qw) windows
    crop: tuple                # (row0, col0, h, w) of the image in the accumulator


def make_plan(img, kernels, m, ident, b, support, pr, pp, chunk) -> Plan:
    """The windows to compute, grouped by what they need (copy, or an FFT
    size), only those that reach the image's frame and whose neighbourhood
    is not all zero. ``support``: (nph, npw) the kernels' half-widths."""

    h, w, c_in = img.shape
    nph, npw = kernels.shape[:2]
    k = kernels.shape[-1]
    r = k // 2
    mode = "reflect" if min(h, w) > 1 else "edge"
    padded = np.pad(img, ((pp, pp + nph * m - h), (pp, pp + npw * m - w), (0, 0)), mode=mode)
    qh, qw = padded.shape[0] // m, padded.shape[1] // m
    ip = np.clip(np.arange(qh) - pp // m, 0, nph - 1)
    jp = np.clip(np.arange(qw) - pp // m, 0, npw - 1)
    win = m + 2 * b
    lead = b + r
    # a window's input is read f x f (its FFT size): past the s = win + 2 hs
    # it needs, real pixels instead of zeros leave the valid part [2 hs,
    # 2 hs + win) of the circular convolution unchanged and save the padding
    extra = max(fft.fast_size(win + 2 * s) - (win + 2 * s) for s in range(r + 1))
    ext = np.pad(padded, ((lead, lead + m + extra), (lead, lead + m + extra), (0, 0)))
    live = live_windows(padded, m, b, r)
    # window i covers padded rows [i m - b, i m + m + b); the frame is [pp, pp + h)
    rows_in = (np.arange(qh) * m - b < pp + h) & (np.arange(qh) * m + m + b > pp)
    cols_in = (np.arange(qw) * m - b < pp + w) & (np.arange(qw) * m + m + b > pp)
    live &= rows_in[:, None] & cols_in[None, :]
    need = np.where(ident[ip][:, jp], -1, support[ip][:, jp])
    size_of = np.array([fft.fast_size(win + 2 * s) for s in range(r + 1)])
    f_need = np.where(need >= 0, size_of[np.maximum(need, 0)], -1)
    jobs = []
    for f_size in np.unique(f_need[live & (need >= 0)]):
        hs = min(r, (int(f_size) - win) // 2)               # the crop grows to fill the FFT size
        ii, jj = np.nonzero(live & (f_need == f_size))
        size = max(16, int(chunk * (72.0 / (win + 2 * hs)) ** 2))
        jobs += [(ii[s:s + size], jj[s:s + size], hs) for s in range(0, len(ii), size)]
    ii, jj = np.nonzero(live & (need < 0))
    jobs += [(ii[s:s + 4 * chunk], jj[s:s + 4 * chunk], -1) for s in range(0, len(ii), 4 * chunk)]
    in_used, in_of = np.unique(pr[:, 0], return_inverse=True)
    k_used, k_of = np.unique(pr[:, 1], return_inverse=True)
    c = len(pr)
    plain = bool(np.array_equal(in_of, np.arange(c)) and np.array_equal(k_of, np.arange(c)))
    tw = blend_window(m, b).astype(np.float32)
    ksum = kernels.sum(axis=(-2, -1), dtype=np.float32)
    return Plan(ext, kernels, ksum, ip, jp, m, b, r, win, pr, in_used, in_of, k_used, k_of, plain,
                np.ascontiguousarray(tw[:, None] * tw[None, :]), jobs,
                (c, qh * m + 2 * b, qw * m + 2 * b), (qh, qw), (b + pp, b + pp, h, w))


def crop_kernels(plan: Plan, ii, jj, hs: int) -> np.ndarray:
    """The windows' kernels (n, C_k used, 2 hs + 1, 2 hs + 1), float32, each
    channel rescaled to its full sum (a constant image stays constant)."""
    r = plan.r
    pi, pj = plan.ip[ii][:, None], plan.jp[jj][:, None]
    ku = plan.k_used[None, :]
    crop = plan.kernels[pi, pj, ku, r - hs:r + hs + 1, r - hs:r + hs + 1].astype(np.float32, copy=False)
    if hs < r:
        full = plan.ksum[pi, pj, ku]
        got = crop.sum(axis=(-2, -1))
        scale = np.where(got != 0, full / np.where(got != 0, got, 1.0), 1.0).astype(np.float32)
        crop = crop * scale[..., None, None]
    return crop


def input_size(plan: Plan, hs: int) -> int:
    """Side of a window's input: win for a copy, else its FFT size (see make_plan)."""
    return plan.win if hs < 0 else fft.fast_size(plan.win + 2 * hs)


def window_inputs(plan: Plan, ii, jj, hs: int, channels) -> np.ndarray:
    """The windows' inputs (n, C, s, s), s = ``input_size``: a strided view
    gathered (~10x faster than fancy-indexing rows and columns)."""
    o = plan.r - max(hs, 0)
    s_in = input_size(plan, hs)
    view = sliding_window_view(plan.ext, (s_in, s_in), axis=(0, 1))
    if len(channels) == plan.ext.shape[-1] and (np.diff(channels) == 1).all() and channels[0] == 0:
        return view[ii * plan.m + o, jj * plan.m + o]
    return view[ii * plan.m + o, jj * plan.m + o][:, channels]


def windows_numpy(plan: Plan, ii, jj, hs: int, be: str) -> np.ndarray:
    """Weighted results (n, c, win, win) float32 of windows (ii, jj)."""
    win = plan.win
    if hs < 0:
        res = window_inputs(plan, ii, jj, hs, plan.pr[:, 0]).astype(np.float32)
    else:
        f = fft.fast_size(win + 2 * hs)
        spec_in = fft.rfft2(window_inputs(plan, ii, jj, hs, plan.in_used), (f, f), be)      # already f x f
        spec_k = fft.rfft2_small(crop_kernels(plan, ii, jj, hs), (f, f), be)
        spec = spec_in * spec_k if plan.plain_pairs else spec_in[:, plan.in_of] * spec_k[:, plan.k_of]
        # circular = linear convolution on the valid part [2 hs, 2 hs + win)
        full = fft.irfft2_rows(spec, (f, f), 2 * hs, win, be)
        res = full[..., 2 * hs:2 * hs + win].astype(np.float32)
    res *= plan.weight
    return res


def new_accumulator(plan: Plan) -> np.ndarray:
    return np.zeros(plan.acc_shape, np.float32)


def parity_classes(plan: Plan, ii, jj):
    """The windows (ii, jj) split by the parity of their patch row and column:
    yields (pi, pj, sel, (nu, nv)), sel their indices and (nu, nv) the
    class's grid. Windows two patches apart are disjoint, so each class is
    added in one indexed add through a strided view of shape (C, nu, win,
    nv, win) whose patch steps are 2 m (the numpy and torch overlap-adds)."""
    for pi in (0, 1):
        for pj in (0, 1):
            sel = np.flatnonzero((ii % 2 == pi) & (jj % 2 == pj))
            if len(sel):
                yield pi, pj, sel, ((plan.grid[0] - pi + 1) // 2, (plan.grid[1] - pj + 1) // 2)


def overlap_add(acc: np.ndarray, plan: Plan, ii, jj, res) -> None:
    """acc[:, i m:i m + win, j m:j m + win] += res[n] for every window: one
    indexed add per parity class (``parity_classes``)."""
    m, win = plan.m, plan.win
    sc, sr, sx = acc.strides
    for pi, pj, sel, (nu, nv) in parity_classes(plan, ii, jj):
        view = as_strided(acc[:, pi * m:, pj * m:], shape=(acc.shape[0], nu, win, nv, win),
                          strides=(sc, 2 * m * sr, sr, 2 * m * sx, sx), writeable=True)
        view[:, ii[sel] // 2, :, jj[sel] // 2, :] += res[sel]


def result(acc: np.ndarray, plan: Plan) -> np.ndarray:
    """The image's frame (h, w, c) float32 out of the accumulator."""
    y0, x0, h, w = plan.crop
    return np.ascontiguousarray(np.moveaxis(acc[:, y0:y0 + h, x0:x0 + w], 0, -1))


def run_numpy(plan: Plan, be: str) -> np.ndarray:
    """The plan on the thread pool (numpy / scipy FFTs), overlap-add serial;
    two chunks in flight ahead of it bound the memory."""
    from ..parallel import thread_pool

    acc = new_accumulator(plan)
    pool = thread_pool()
    pending = []
    for ii, jj, hs in plan.jobs:
        pending.append((ii, jj, pool.submit(windows_numpy, plan, ii, jj, hs, be)))
        if len(pending) > 2:
            a, b_, fut = pending.pop(0)
            overlap_add(acc, plan, a, b_, fut.result())
    for a, b_, fut in pending:
        overlap_add(acc, plan, a, b_, fut.result())
    return result(acc, plan)


def cost(plan: Plan) -> dict:
    """Windows per kind, for reports: {'fft': n, 'copy': n}."""
    n_fft = sum(len(ii) for ii, _, hs in plan.jobs if hs >= 0)
    return {"fft": n_fft, "copy": sum(len(ii) for ii, _, hs in plan.jobs if hs < 0)}
