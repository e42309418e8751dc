"""Depth- and field-aware non-blind deconvolution of a capture (numpy).

The capture is what ``render.simulate`` makes: every m x m patch of the
sharp image on the sensor blurred with the lens's PSF for its field, azimuth
and depth, blended with tent weights, plus sensor noise. The deconvolution
inverts that model patch by patch with the same PSF map (same library, same
patches, same kernels): each patch's window (the 2m tent region and some
context) is Wiener-deconvolved (``wiener``) with its kernel, and the windows
are blended back with the same tent weights.

Depth inside a patch: a patch's kernel is the PSF at the patch's mean
inverse depth; pixels of its window whose inverse depth differs from that by
more than half of ``layer_step_diopters`` take the window deconvolved with
the PSF at their own depth, rounded to that step (a depth layer). Most
patches hold one depth and cost one window; a patch on an occlusion edge
costs one window per depth layer it holds.

Regularisation: lambda = ``weight`` x the noise variance at the window's
mean brightness (``noise``: the sensor model, or estimated from the capture)
over the image's gradient power, measured in each window from the capture
(its gradient energy less the noise's, over the kernel's) on the pixels at
the window's own depth (a window on a near object would otherwise take the
sharper wall behind it for its own texture, and ring: a factory room's near
pillar, MOS-S2 at 12.2 um, 19.1 dB against 23.5 dB): a factory room's
smooth walls and a photograph's texture need priors orders of magnitude
apart, and one fixed weight served one of them at the other's expense
(MOS-S1 at 12.2 um: synthetic scene 23.7 dB either way, factory room 31.5 dB
fixed against 33.9 adaptive, capture 32.0).
Clipped highlights are not deconvolved (their light is lost): pixels within
the kernel's reach of a clipped pixel keep the capture's value. The output is
never negative, and at most 1 where the capture is a sensor's (at most 1);
within a kernel radius of the frame's edge it fades to the capture (that
band holds light from outside the frame). It is
on the capture's grid, so it aligns with ``simulate``'s sharp image (the
distortion is the capture's too).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputRangeError
from ..render import fft
from ..render.geometry import ImageGeometry
from ..render.psfmap import PSFMap, psf_map
from ..psf.library import valid_depth_mask
from ..render.base import check_patch
from ..psf.sources import lens_library
from .noise import NoiseModel, estimate_noise
from .wiener import WindowLayout, deconvolve_all, layout_for

# weight of the gradient prior per unit of noise variance, and the layer
# step: chosen by `python -m lab report correction` (error against time, held-out)
DEFAULT_WEIGHT = 6.0
DEFAULT_LAYER_STEP = None
METHODS = ("wiener", "hqs")
# the least noise a capture has: 8-bit quantisation's, (1/255)^2 / 12; a
# noise-free render estimated at zero noise would otherwise get no prior at
# all and ring with the model's own error (PSFs per patch, windows cut short)
QUANTISATION_VARIANCE = 1.0 / (12.0 * 255.0 ** 2)
PRIORS = ("adaptive", "fixed")


@dataclass(frozen=True)
class DeconvOptions:
    """What the deconvolution does (checked when made).

    method: 'wiener' (one closed-form filter a window) or 'hqs'
    (half-quadratic splitting with a total-variation prior, ``iterations``
    rounds of three FFTs a window, started from the Wiener result).
    prior: 'adaptive' (the image's gradient power measured in each window,
    lambda = weight x noise variance / that power) or 'fixed' (lambda =
    weight x noise variance: one image statistic for every scene).
    patch: the PSF map's patch (px, even; the simulation's 16 by default:
    32 takes a third of the time and is as exact for the MOS lenses, but a
    fast lens's PSF changes with depth within 32 px: the 6P at 50 um on the
    synthetic scene lost 2.6 dB against 16).
    layer_step_diopters: depth layers inside a patch, 1/m apart; None: one
    depth per patch (the patch's mean). one_depth_m: one depth for the whole
    image (the depth-unaware baseline). weight: the prior's weight per unit
    of noise variance. noise: the sensor's model, None to estimate it from
    the capture. clip_level: a capture value at or above it is clipped
    (linear, per channel). pad: context of each window, px (None: from the
    kernel size)."""

    method: str = "wiener"
    iterations: int = 4
    prior: str = "adaptive"
    patch: int = 16
    layer_step_diopters: float | None = DEFAULT_LAYER_STEP
    one_depth_m: float | None = None
    weight: float = DEFAULT_WEIGHT
    noise: NoiseModel | None = None
    clip_level: float = 0.98
    pad: int | None = None
    chunk: int = 64
    fft_backend: str | None = None

    def __post_init__(self):
        if self.prior not in PRIORS:
            raise InputRangeError("prior", self.prior, " or ".join(PRIORS))
        if self.method not in METHODS:
            raise InputRangeError("method", self.method, " or ".join(METHODS))
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 50):
            raise InputRangeError("iterations", self.iterations, "an integer in [1, 50] (method 'hqs')")
        check_patch(self.patch)
        s = self.layer_step_diopters
        if s is not None and not (math.isfinite(s) and 0.005 <= s <= 2.0):
            raise InputRangeError("layer_step_diopters", s, "a number in [0.005, 2] 1/m, or None (one depth a patch)")
        if self.one_depth_m is not None and not self.one_depth_m > 0:
            raise InputRangeError("one_depth_m", self.one_depth_m, "> 0 metres or inf")
        if not (math.isfinite(self.weight) and self.weight > 0):
            raise InputRangeError("weight", self.weight, "a finite number > 0")
        if not (0.0 < self.clip_level <= 1e6):
            raise InputRangeError("clip_level", self.clip_level, "> 0 (linear light; 0.98 for a [0, 1] sensor)")
        if self.pad is not None and not (isinstance(self.pad, int) and 2 <= self.pad <= 512):
            raise InputRangeError("pad", self.pad, "an integer in [2, 512] px, or None")
        if not (isinstance(self.chunk, int) and self.chunk >= 1):
            raise InputRangeError("chunk", self.chunk, "an integer >= 1")
        fft.backend(self.fft_backend)


@dataclass
class DeconvResult:
    image: np.ndarray                     # (H, W, 3) float32 linear, the capture's grid
    info: dict = field(default_factory=dict)
    psf_map: PSFMap | None = None


def _check(capture, depth_m, geometry: ImageGeometry):
    y = np.asarray(capture, np.float32)
    if y.ndim != 3 or y.shape[2] != 3:
        raise InputRangeError("capture shape", y.shape, "(H, W, 3)")
    if not np.isfinite(y).all():
        raise InputRangeError("capture", "non-finite values", "finite linear RGB")
    d = np.asarray(depth_m, np.float64)
    if d.shape != y.shape[:2]:
        raise InputRangeError("depth map shape", d.shape, f"{y.shape[:2]}, the capture's")
    if (geometry.height, geometry.width) != y.shape[:2]:
        raise InputRangeError("capture shape", y.shape[:2], f"({geometry.height}, {geometry.width}), its geometry's")
    return y, d


def deconvolve(capture, depth_m, lens, options: DeconvOptions = DeconvOptions(), *,
               geometry: ImageGeometry | None = None, library=None, settings=None, progress=None) -> DeconvResult:
    """The sharp image on the sensor from a ``capture`` (H, W, 3) linear and
    its depth (H, W) metres from the lens's first vertex (NaN, 0 or negative:
    unknown; those pixels take their patch's depth, and a patch with none is
    left as it is). geometry: where the capture lies on the sensor (default:
    it spans the sensor's diagonal). library: the lens's PSFs at the
    capture's pixel pitch (any source's); without one,
    ``psf.sources.lens_library``'s with ``settings``. ``progress(done, total)`` as windows finish."""
    t0 = time.perf_counter()
    geometry = geometry or ImageGeometry.full_sensor(lens, *np.shape(capture)[:2])
    y, d = _check(capture, depth_m, geometry)
    if library is None:
        library = lens_library(lens, geometry, settings, fit_depth_m=d)
    m = options.patch
    base = psf_map(library, geometry, d, m, fixed_depth_m=options.one_depth_m, clamp_field=True)
    t_map = time.perf_counter() - t0
    noise = options.noise if options.noise is not None else estimate_noise(y)
    plan = _layer_plan(d, base, library, geometry, options)
    lay = layout_for(m, base.kernels.shape[-1], options.pad)
    # the adaptive prior's image statistic from each window's own depth (one depth for all: the whole window)
    own = options.prior == "adaptive" and options.one_depth_m is None
    grad_px = _own_depth_gradients(y, d, base, plan, m, library.grid.far_m) if own else None
    out, n_windows = _blend_windows(y, plan, noise, lay, options, progress, grad_px)
    reach = int(base.kernels.shape[-1] // 2)
    out = _keep_clipped(y, _fade_to_border(y, out, reach), options.clip_level, reach)
    info = {"method": "deconvolution", "algorithm": options.method, "patch": m, "windows": n_windows,
            "patches": int(base.identity.size),
            "layer_step_diopters": None if options.one_depth_m is not None else options.layer_step_diopters,
            "one_depth_m": options.one_depth_m, "weight": options.weight, "prior": options.prior,
            "noise": {"gain": noise.gain, "floor": noise.floor, "given": options.noise is not None},
            "kernel_px": int(base.kernels.shape[-1]), "pad_px": lay.pad,
            "clipped_px": int((y >= options.clip_level).any(axis=2).sum()),
            "seconds": {"psf_map": round(t_map, 3), "total": round(time.perf_counter() - t0, 3)}}
    return DeconvResult(out, info, base)


# ------------------------------------------------------------------ depth layers
@dataclass
class _Plan:
    """Every (patch, layer) window: its patch, its kernel, and which pixels of
    the patch's 2m core take it."""

    patch_ij: np.ndarray          # (n, 2) patch indices
    kernels: np.ndarray           # (n, C, k, k)
    offset: np.ndarray            # (n,) the layer, in steps from the patch's own depth
    offsets: np.ndarray | None    # (nph, npw, 2m, 2m) each core pixel's layer (None: all 0)
    identity: np.ndarray          # (nph, npw) patches left as they are


def _core_inverse_depth(d: np.ndarray, m: int, nph: int, npw: int, far_m: float):
    """(nph, npw, 2m, 2m) inverse depth of each patch's tent region (NaN: unknown)."""
    valid = valid_depth_mask(d)
    inv = np.where(valid, np.where(d >= far_m, 0.0, 1.0 / np.where(valid, d, 1.0)), np.nan)
    b = m // 2
    full = np.pad(inv, ((b, nph * m - d.shape[0] + b), (b, npw * m - d.shape[1] + b)), constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(full, (2 * m, 2 * m))
    return win[::m, ::m][:nph, :npw]


def _layer_plan(d, base: PSFMap, library, geometry, options: DeconvOptions) -> _Plan:
    m = options.patch
    nph, npw = base.identity.shape
    todo = ~base.identity
    ij = np.argwhere(todo)
    step = options.layer_step_diopters
    if options.one_depth_m is not None or step is None:
        return _Plan(ij, base.kernels[todo], np.zeros(len(ij), np.int64), None, base.identity)
    far = library.grid.far_m
    own = np.where(np.isfinite(base.depth_m), 1.0 / np.where(np.isfinite(base.depth_m), base.depth_m, 1.0), 0.0)
    own = np.where(base.depth_m >= far, 0.0, own)
    core = _core_inverse_depth(d, m, nph, npw, far)
    off = np.rint((core - own[:, :, None, None]) / step)
    off = np.where(np.isfinite(off), off, 0.0).astype(np.int64)
    off[base.identity] = 0
    patch_ij, kernels, offset = [ij], [base.kernels[todo]], [np.zeros(len(ij), np.int64)]
    present = np.zeros((nph, npw), bool)
    for k in np.unique(off[todo]):
        if k == 0:
            continue
        present[:] = (off == k).any(axis=(2, 3)) & todo
        inv_k = np.maximum(own + k * step, 0.0)
        depth_k = np.where(present, np.where(inv_k > 0, 1.0 / np.where(inv_k > 0, inv_k, 1.0), np.inf), np.nan)
        pm = psf_map(library, geometry, np.kron(depth_k, np.ones((m, m)))[:geometry.height, :geometry.width], m,
                     clamp_field=True)
        where = np.argwhere(present & ~pm.identity)
        patch_ij.append(where)
        kernels.append(pm.kernels[present & ~pm.identity])
        offset.append(np.full(len(where), k, np.int64))
    return _Plan(np.concatenate(patch_ij), np.concatenate(kernels), np.concatenate(offset), off, base.identity)


# ------------------------------------------------------------------ the windows and their blend
def _own_depth_gradients(y, d, base: PSFMap, plan: _Plan, m: int, far_m: float, tol: float = 0.1) -> np.ndarray:
    """(n, C): the capture's mean squared gradient over the pixels of each
    window's core that lie within ``tol`` diopters of its patch's depth (the
    image statistic its prior needs; a near object's window must not take
    the sharper detail of the wall behind it for its own)."""
    h, w = d.shape
    nph, npw = plan.identity.shape
    b = m // 2
    gy = np.zeros_like(y)
    gx = np.zeros_like(y)
    gy[:-1] = y[1:] - y[:-1]
    gx[:, :-1] = y[:, 1:] - y[:, :-1]
    g2 = (gy ** 2 + gx ** 2).astype(np.float32)
    full = np.pad(g2, ((b, nph * m - h + b), (b, npw * m - w + b), (0, 0)))
    win = np.lib.stride_tricks.sliding_window_view(full, (2 * m, 2 * m), axis=(0, 1))[::m, ::m][:nph, :npw]
    core = _core_inverse_depth(d, m, nph, npw, far_m)
    own = np.where(np.isfinite(base.depth_m), 1.0 / np.where(np.isfinite(base.depth_m), base.depth_m, 1.0), 0.0)
    own = np.where(base.depth_m >= far_m, 0.0, own)
    near = np.abs(core - own[:, :, None, None]) <= tol            # NaN depth: False
    i, j = plan.patch_ij[:, 0], plan.patch_ij[:, 1]
    sel = near[i, j].astype(np.float32)                          # (n, 2m, 2m)
    g = win[i, j]                                                  # (n, C, 2m, 2m)
    cnt = sel.sum(axis=(1, 2))
    tot = np.einsum("ncxy,nxy->nc", g, sel)
    return np.where(cnt[:, None] > 0, tot / np.maximum(cnt, 1)[:, None], g.mean(axis=(2, 3))).astype(np.float32)


def _blend_windows(y: np.ndarray, plan: _Plan, noise: NoiseModel, lay: WindowLayout, options: DeconvOptions,
                   progress, grad_px=None):
    from ..render.windows import blend_window

    m, b = options.patch, options.patch // 2
    h, w, c = y.shape
    nph, npw = plan.identity.shape
    lead = b + lay.pad                                   # padded pixel (0, 0) is image pixel (-lead, -lead)
    padded = np.pad(y, ((lead, nph * m - h + lead), (lead, npw * m - w + lead), (0, 0)), mode="reflect")
    origins = plan.patch_ij * m                          # window of patch (i, j) starts at padded (i m, j m)
    var = _noise_variance(padded, origins, lay, noise)
    be = fft.backend(options.fft_backend)
    cores = deconvolve_all(padded, origins, plan.kernels, var, lay, be, weight=options.weight,
                           adaptive=options.prior == "adaptive", chunk=options.chunk, on_chunk=progress,
                           iterations=options.iterations if options.method == "hqs" else 0, grad_px=grad_px)
    tent = blend_window(m, b).astype(np.float32)
    tent2 = tent[:, None] * tent[None, :]
    acc = np.zeros((nph * m + 2 * b, npw * m + 2 * b, c), np.float32)
    # the tents sum to 1 between patches, not at the frame's border (no patch beyond it): divide by their sum
    wsum = np.zeros(acc.shape[:2], np.float32)
    for n, (i, j) in enumerate(plan.patch_ij):
        wgt = tent2 if plan.offsets is None else tent2 * (plan.offsets[i, j] == plan.offset[n])
        acc[i * m:i * m + 2 * m, j * m:j * m + 2 * m] += np.moveaxis(cores[n], 0, -1) * wgt[:, :, None]
        wsum[i * m:i * m + 2 * m, j * m:j * m + 2 * m] += wgt
    for i, j in np.argwhere(plan.identity):              # no depth known: the capture as it is
        r0, c0 = lay.pad + i * m, lay.pad + j * m
        acc[i * m:i * m + 2 * m, j * m:j * m + 2 * m] += padded[r0:r0 + 2 * m, c0:c0 + 2 * m] * tent2[..., None]
        wsum[i * m:i * m + 2 * m, j * m:j * m + 2 * m] += tent2
    return acc[b:b + h, b:b + w] / wsum[b:b + h, b:b + w, None], len(plan.patch_ij)


def _noise_variance(padded, origins, lay: WindowLayout, noise: NoiseModel) -> np.ndarray:
    """(n, C): the noise variance at each window core's mean brightness."""
    p, core = lay.pad, lay.core
    s = np.cumsum(np.cumsum(np.pad(padded, ((1, 0), (1, 0), (0, 0))), axis=0), axis=1)
    r0, c0 = origins[:, 0] + p, origins[:, 1] + p
    r1, c1 = r0 + core, c0 + core
    total = s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0]
    return (noise.variance(total / core ** 2) + QUANTISATION_VARIANCE).astype(np.float32)


def _fade_to_border(y: np.ndarray, out: np.ndarray, reach: int) -> np.ndarray:
    """Within ``reach`` px of the frame's edge the capture holds light from
    outside the frame, which no deconvolution knows: the result fades
    linearly to the capture there (on a frame not much larger than the
    kernel, a deconvolution of mirrored context made the capture worse)."""
    h, w = y.shape[:2]
    dist = np.minimum(np.minimum(np.arange(h), np.arange(h)[::-1])[:, None],
                      np.minimum(np.arange(w), np.arange(w)[::-1])[None, :])
    ramp = np.clip((dist + 0.5) / max(reach, 1), 0.0, 1.0).astype(np.float32)[..., None]
    return y + ramp * (out - y)


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """True within r px (a square) of a True pixel: box sums of a summed-area table."""
    s = np.pad(np.cumsum(np.cumsum(mask.astype(np.int64), 0), 1), ((1, 0), (1, 0)))
    h, w = mask.shape
    r0, r1 = np.clip(np.arange(h) - r, 0, h), np.clip(np.arange(h) + r + 1, 0, h)
    c0, c1 = np.clip(np.arange(w) - r, 0, w), np.clip(np.arange(w) + r + 1, 0, w)
    return (s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]) > 0


def _keep_clipped(y: np.ndarray, out: np.ndarray, level: float, reach: int) -> np.ndarray:
    """Light is never negative, and a sensor's capture (values <= 1) has a
    sharp image that saturates at 1 too: the output is clipped to that range
    (ringing beyond it is the inverse filter's, not the scene's). Within
    ``reach`` px of a clipped pixel, the capture's value."""
    out = np.clip(out, 0.0, 1.0 if float(y.max()) <= 1.0 else None)
    clipped = (y >= level).any(axis=2)
    if not clipped.any():
        return out.astype(np.float32)
    return np.where(_dilate(clipped, reach)[..., None], y, out).astype(np.float32)
