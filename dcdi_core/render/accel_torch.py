"""torch as an optional accelerator of the simulation (``accelerator="torch"``).

Outside Blender torch (CPU) is installed with the project; inside Blender it
is not, and nothing here is imported unless a caller asks for it: torch is
imported lazily, in the functions below, never at module level, and the
default everywhere is numpy. What runs in torch is the same plan and the
same maths as the numpy path, so the results equal it to float32 rounding
(tested):

- the PSF map's kernel rotation (``psfmap._rotate_flat_fast``): the
  bilinear taps by ``grid_sample``, batched over all patches of one support
  size (torch's flat gathers measured 3x slower than numpy's ``take``);
- the convolution (``convolve_fast``): each group of windows of one FFT size
  gathered through ``unfold`` views, transformed by ``torch.fft.rfft2`` in
  one batch, and overlap-added per parity class.

torch's own intra-op threads do the parallel work (its default thread
count); the calls run on the caller's thread, not on the project's pool.
"""
from __future__ import annotations

import importlib.util

import numpy as np


def available() -> bool:
    """True when torch can be imported here (False in Blender's Python)."""
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):           # a blocked or broken torch
        return False


def _torch():
    try:
        import torch
    except ImportError as e:                    # pragma: no cover - depends on the environment
        raise ValueError("accelerator 'torch' asked for, but torch cannot be imported here "
                         "(Blender's Python has none): leave the accelerator out for numpy") from e
    return torch


def rotate_flat(src, outward, k: int, target_sum):
    """``psfmap._rotate_flat_fast`` in torch: src (n, C, k*k) float32 tensor,
    outward (n, 2), target_sum (n, C) -> (n, C, k*k) tensor. The bilinear
    taps by ``grid_sample`` (zeros outside, pixel centres at the corners'
    convention ``align_corners=True``): the same weights to float32 rounding
    of the normalised coordinates; the centre's peak kept in place as there."""
    torch = _torch()
    import torch.nn.functional as F

    r = k // 2
    n, c, kk = src.shape
    centre = r * k + r
    src = src.clone()
    peak = src[:, :, centre].clone()
    if k >= 3:
        ring = [centre + dy * k + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
        peak = torch.clamp(peak - src[:, :, ring].amax(dim=-1), min=0.0)
    src[:, :, centre] -= peak
    if k == 1:
        acc = src + peak[..., None]
    else:
        ax = torch.arange(k, dtype=torch.float32) - r
        dr, dc = torch.meshgrid(ax, ax, indexing="ij")
        ur, uc = outward[:, 0, None, None], outward[:, 1, None, None]
        a = dr * ur + dc * uc + r            # along the radial axis -> source row
        b = -dr * uc + dc * ur + r           # tangential -> source column
        grid = torch.stack([b * (2.0 / (k - 1)) - 1.0, a * (2.0 / (k - 1)) - 1.0], dim=-1)
        acc = F.grid_sample(src.reshape(n, c, k, k), grid, mode="bilinear", padding_mode="zeros",
                            align_corners=True).reshape(n, c, kk)
        acc[:, :, centre] += peak
    after = acc.sum(dim=-1, keepdim=True)
    acc *= torch.where(after > 0, target_sum[..., None] / torch.where(after > 0, after, torch.ones_like(after)),
                       torch.zeros_like(after))
    return acc


def rotated_patch_kernels(plan, outward, kernels_flat, where):
    """``psfmap._rotated_patch_kernels`` in torch (same arguments, writes
    kernels_flat[where]); returns the half-widths computed."""
    torch = _torch()
    entry, weight, target, half, psf = plan
    r = psf.shape[-1] // 2
    ro = kernels_flat.shape[-1] // 2
    psf_t = torch.from_numpy(np.ascontiguousarray(psf, dtype=np.float32))
    out_t = torch.from_numpy(np.ascontiguousarray(outward, dtype=np.float32))
    w_t, tgt_t = torch.from_numpy(weight), torch.from_numpy(target.astype(np.float32))
    for h in np.unique(half):
        sel = np.nonzero(half == h)[0]
        kc = 2 * int(h) + 1
        sel_t = torch.from_numpy(sel)
        g = psf_t[:, :, r - h:r + h + 1, r - h:r + h + 1][torch.from_numpy(entry[sel])]   # (n, 4, C, kc, kc)
        blend = torch.einsum("nq,nqx->nx", w_t[sel_t], g.reshape(len(sel), 4, -1)).reshape(len(sel), 3, kc * kc)
        rot = rotate_flat(blend, out_t[sel_t], kc, tgt_t[sel_t])
        kernels_flat[where[sel], :, ro - h:ro + h + 1, ro - h:ro + h + 1] = rot.reshape(len(sel), 3, kc, kc).numpy()
    return half


def run_plan(plan) -> np.ndarray:
    """``convolve_fast.run_numpy`` in torch: the same windows, weights and
    overlap-add; returns float32 (h, w, c) numpy."""
    from .convolve_fast import crop_kernels, input_size

    torch = _torch()
    acc = torch.zeros(plan.acc_shape, dtype=torch.float32)
    ext = torch.from_numpy(np.ascontiguousarray(plan.ext, dtype=np.float32))
    weight = torch.from_numpy(plan.weight)
    m, win = plan.m, plan.win
    in_used = torch.from_numpy(plan.in_used)
    for ii, jj, hs in plan.jobs:
        o = plan.r - max(hs, 0)
        s_in = input_size(plan, hs)
        # windows at rows i m + o: an unfold view with step m, then one gather
        view = ext[o:, o:].unfold(0, s_in, m).unfold(1, s_in, m)              # (rows, cols, C, s, s)
        ii_t, jj_t = torch.from_numpy(ii), torch.from_numpy(jj)
        if hs < 0:
            res = view[ii_t, jj_t][:, torch.from_numpy(plan.pr[:, 0])]
        else:
            f = _fast_size(win + 2 * hs)
            x = view[ii_t, jj_t][:, in_used]
            kern = torch.from_numpy(crop_kernels(plan, ii, jj, hs))
            spec_in = torch.fft.rfft2(x, s=(f, f))
            spec_k = torch.fft.rfft2(kern, s=(f, f))
            if plan.plain_pairs:
                spec = spec_in * spec_k
            else:
                spec = spec_in[:, torch.from_numpy(plan.in_of)] * spec_k[:, torch.from_numpy(plan.k_of)]
            res = torch.fft.irfft2(spec, s=(f, f))[..., 2 * hs:2 * hs + win, 2 * hs:2 * hs + win]
        res = res * weight
        _overlap_add(torch, acc, plan, ii, jj, res)
    y0, x0, h, w = plan.crop
    return np.ascontiguousarray(acc[:, y0:y0 + h, x0:x0 + w].permute(1, 2, 0).numpy())


def _overlap_add(torch, acc, plan, ii, jj, res) -> None:
    """``convolve_fast.overlap_add`` on a torch accumulator."""
    from .convolve_fast import parity_classes

    m, win = plan.m, plan.win
    sc, sr, sx = acc.stride()
    for pi, pj, sel, (nu, nv) in parity_classes(plan, ii, jj):
        view = acc.as_strided((acc.shape[0], nu, win, nv, win), (sc, 2 * m * sr, sr, 2 * m * sx, sx),
                              pi * m * sr + pj * m * sx)
        uu, vv = torch.from_numpy(ii[sel] // 2), torch.from_numpy(jj[sel] // 2)
        view[:, uu, :, vv, :] += res[torch.from_numpy(sel)]


def _fast_size(n: int) -> int:
    from .fft import fast_size
    return fast_size(int(n))
