"""Metric depth from a capture's own blur: for each tile, the depth of the
lens's PSF library whose blur best explains the tile's spectrum
(``evidence``), a confidence from how sharply the evidence picks it, and
uncertain tiles filled from confident ones along the capture's edges
(``fill``).

Units: depths in metres, inverse depths (diopters) in 1/m, sizes in pixels.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputRangeError
from . import evidence, fill


@dataclass(frozen=True)
class DepthFromBlurOptions:
    """How :func:`estimate_depth` reads depth from blur, checked when made.

    tile: px between evidence windows (one estimate per tile). window: the
    side of each window (px, >= tile; about four PSF widths: larger windows
    see more texture and blur less of a depth edge into their neighbours).
    max_frequency: the highest spatial frequency used (cycles/px; above it
    these lenses pass only noise). colour_residual: the colour texture's
    power beside the shared texture's (0: grey scenes; the chromatic cue
    then carries most). model_error: the share of the sharp texture's power
    the PSFs may fail to explain (their error; see ``evidence``).
    amplitude_steps: the texture amplitudes tried about
    each window's own estimate (the likelihood is minimised over them).
    hypothesis_step: every n-th depth bin of the library is a hypothesis.
    kernel_share: one PSF for each kernel_share x kernel_share tiles (the
    one at their block's centre). sharpness_px: the sharp image's own
    softness tried (a Gaussian's sigma, px; the likelihood is minimised
    over them): a render's pixel filter or a sensor's pixel is not defocus.
    aggregate: each tile's evidence joined with its neighbours' within
    this many tiles (0: none), weighted by how alike their mean colours
    are (``aggregate_colour``: the log-RGB distance's scale).
    temperature: the evidence's scale in the posterior the estimate and
    the fill use (the windows' frequencies are not independent: > 1 widens
    the posterior). confidence_temperature: the same for the confidence and
    the posterior handed on (``TilePosterior``): wider, so that a tile of
    confidence c lies within the tolerance of the truth about a share c of
    the time (calibrated on natural-statistics, dead-leaves and plane
    frames; docs/depth.md).
    refine_within: a learned refinement may move a tile's depth only
    within these quantiles of its posterior (what its blur allows; None:
    anywhere): trained on the factory's scenes, it moved photograph-like
    frames' depths far from their evidence (docs/depth.md).
    tolerance: the confidence is the posterior's mass within this relative
    depth error of the estimate. fill_radius: the guided filter's
    radius (px; None: the tile), fill_eps its edge threshold (the guide's
    variance units)."""

    tile: int = 32
    window: int = 64
    max_frequency: float = 0.71
    colour_residual: float = 0.02
    model_error: float = 0.01
    amplitude_steps: tuple = (2.0, 8.0, 32.0)
    hypothesis_step: int = 2
    kernel_share: int = 2
    sharpness_px: tuple = (0.0, 0.7, 1.4)
    texture_slopes: tuple = (2.0,)
    aggregate: int = 1
    aggregate_colour: float = 0.2
    temperature: float = 30.0
    confidence_temperature: float = 60.0
    refine_within: tuple | None = (0.1, 0.9)
    tolerance: float = 0.15
    fill_radius: int | None = None
    fill_eps: float = 0.1
    fill: str = "guided"
    fill_colour: float = 0.15

    def __post_init__(self):
        def integer(name, lo, hi):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise InputRangeError(name, v, f"an integer in [{lo}, {hi}]")

        def number(name, lo, hi, lo_open=True):
            v = getattr(self, name)
            ok = isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) and np.isfinite(v)
            if not ok or not ((v > lo) if lo_open else (v >= lo)) or v > hi:
                raise InputRangeError(name, v, f"a number in {'(' if lo_open else '['}{lo}, {hi}]")

        integer("tile", 8, 256)
        integer("window", 16, 512)
        if self.window < self.tile:
            raise InputRangeError("window", self.window, f">= the tile ({self.tile} px)")
        integer("hypothesis_step", 1, 16)
        integer("kernel_share", 1, 8)
        integer("aggregate", 0, 8)
        number("aggregate_colour", 0.0, 1e3)
        number("max_frequency", 0.0, 0.71)
        number("colour_residual", 0.0, 10.0, lo_open=False)
        number("model_error", 0.0, 1.0, lo_open=False)
        number("temperature", 0.0, 1e6)
        number("confidence_temperature", 0.0, 1e6)
        if self.refine_within is not None:
            q = np.asarray(self.refine_within, dtype=float)
            if q.shape != (2,) or not (np.isfinite(q).all() and 0.0 <= q[0] < q[1] <= 1.0):
                raise InputRangeError("refine_within", self.refine_within, "None, or two quantiles 0 <= low < high <= 1")
        number("tolerance", 0.0, 1.0)
        number("fill_eps", 0.0, 1e3)
        number("fill_colour", 0.0, 10.0)
        if self.fill not in ("guided", "bilateral"):
            raise InputRangeError("fill", self.fill, "'guided' or 'bilateral'")
        if self.fill_radius is not None:
            integer("fill_radius", 1, 1024)
        sharp = np.asarray(self.sharpness_px, dtype=float)
        if sharp.ndim != 1 or sharp.size == 0 or not (np.isfinite(sharp).all() and (sharp >= 0).all()):
            raise InputRangeError("sharpness_px", self.sharpness_px, "one or more numbers >= 0 (px)")
        slopes = np.asarray(self.texture_slopes, dtype=float)
        if slopes.ndim != 1 or slopes.size == 0 or not (np.isfinite(slopes).all() and (slopes >= 0.5).all()
                                                         and (slopes <= 4).all()):
            raise InputRangeError("texture_slopes", self.texture_slopes, "one or more numbers 0.5 to 4")
        steps = np.asarray(self.amplitude_steps, dtype=float)
        if steps.ndim != 1 or steps.size == 0 or not (np.isfinite(steps).all() and (steps > 0).all()):
            raise InputRangeError("amplitude_steps", self.amplitude_steps, "one or more numbers > 0")


@dataclass
class TilePosterior:
    """What the evidence says of each tile, for a decision downstream
    (``app.depth.DofDepthRule``): ``depths_m`` (n,) the hypotheses (the
    library's far limit for infinity), ``posterior`` (n, nph, npw) their
    probabilities, ``estimate_m`` (nph, npw) the tile's estimate (refined
    where a refinement ran), ``camera_blur_px`` (n, nph, npw) the camera
    lens's blur diameter at each hypothesis there (``blur_diameter_px``),
    ``tile_px`` the tile's side."""

    depths_m: np.ndarray
    posterior: np.ndarray
    estimate_m: np.ndarray
    camera_blur_px: np.ndarray
    tile_px: int


def blur_diameter_px(kernels: np.ndarray) -> np.ndarray:
    """The diameter (px) of the uniform disc as concentrated as the green
    channel of kernels (..., 3, k, k): sqrt(4 / (pi sum g^2)) for g summing
    to 1 (a disc of diameter D has sum g^2 = 4 / (pi D^2); a point, 1.13
    px). Unlike the RMS radius, a sharp core in a faint halo (these
    singlets' spherical aberration) counts as sharp, as it does for texture."""
    g = np.maximum(kernels[..., 1, :, :], 0.0)
    total = g.sum((-1, -2), dtype=np.float64)
    squares = np.einsum("...ij,...ij->...", g, g, dtype=np.float64)
    return np.sqrt(4.0 / np.pi * np.maximum(total, 1e-12) ** 2 / np.maximum(squares, 1e-24))


@dataclass
class DepthEstimate:
    """``depth_m`` (H, W) float32 metres within the library's [near, far];
    ``confidence`` (H, W) float32 in [0, 1] (the posterior's mass within
    the tolerance of the estimate; 0 where the tile was clipped or had no
    texture above the noise); the per-tile figures before filling
    (``tile_diopters`` 1/m, ``tile_confidence``); ``info``: the hypotheses,
    noise model and seconds."""

    depth_m: np.ndarray
    confidence: np.ndarray
    tile_diopters: np.ndarray
    tile_confidence: np.ndarray
    info: dict = field(default_factory=dict)
    tile_features: np.ndarray | None = None
    posterior: TilePosterior | None = None


# what `tile_features` stacks, in order: a learned refinement reads them by position
FEATURES = ("posterior (one per hypothesis)", "log depth of the estimate", "confidence", "field",
            "log texture power over noise", "log mean colour R", "G", "B")


def tile_features(post, est, conf, spectra, geometry, tile: int) -> np.ndarray:
    """Per tile (C, nph, npw) float32: the posterior over the hypotheses,
    the estimate's log depth (m), its confidence, the field of the tile's
    centre, the log of the window's texture power over its noise, and the
    log of its mean colour (``FEATURES``)."""
    nph, npw = spectra.tiles
    rows = (np.arange(nph) + 0.5) * tile
    cols = (np.arange(npw) + 0.5) * tile
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    fld = np.minimum(geometry.field(rr.ravel(), cc.ravel()), 1.5)
    over = spectra.power.sum((1, 2)) / np.maximum((spectra.noise.sum(1) * spectra.count.sum()), 1e-12)
    colour = np.log(np.maximum(spectra.mean, 1e-4)).T
    stack = np.concatenate([post, np.log(est)[None], conf[None], fld[None], np.log(np.maximum(over, 1e-6))[None],
                            colour], 0)
    return stack.reshape(len(stack), nph, npw).astype(np.float32)


def check_capture(capture) -> np.ndarray:
    img = np.asarray(capture)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("capture shape", img.shape, "(H, W, 3) linear RGB")
    if min(img.shape[:2]) < 16:
        raise InputRangeError("capture size", img.shape[:2], "at least 16 x 16 px")
    img = img.astype(np.float32, copy=False)
    bad = ~np.isfinite(img)
    if bad.any():
        raise InputRangeError("capture", f"{int(bad.sum())} NaN or infinite values", "finite linear values")
    return img


def _posterior(nll: np.ndarray, depths_m: np.ndarray, temperature: float, tolerance: float):
    """(estimate (n,) metres, confidence (n,), posterior (hypotheses, n)) from the NLL (hypotheses, n)
    of hypotheses at ``depths_m`` (finite: the library's far limit for
    infinity). The estimate minimises the expected relative depth error
    under the posterior p ~ exp(-NLL / temperature): the median of the
    hypotheses weighted by p / depth. The confidence: the posterior's mass
    within ``tolerance`` relative error of the estimate."""
    p = np.exp(-(nll - nll.min(0)) / temperature)
    p /= p.sum(0)
    order = np.argsort(depths_m)
    z = depths_m[order]
    wz = p[order] / z[:, None]
    cum = np.cumsum(wz, 0)
    k = (cum < 0.5 * cum[-1]).sum(0)
    est = z[np.minimum(k, len(z) - 1)]
    conf = (p * (np.abs(depths_m[:, None] - est) <= tolerance * est)).sum(0)
    return est, conf, p


def _quantiles(post: np.ndarray, depths_m: np.ndarray, q: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The (low, high) quantiles ``q`` (n,) of the posterior (hypotheses, n) over ``depths_m`` (hypotheses,)."""
    order = np.argsort(depths_m)
    z, cum = depths_m[order], np.cumsum(post[order], 0)
    lo = z[np.minimum((cum < q[0]).sum(0), len(z) - 1)]
    hi = z[np.minimum((cum < q[1]).sum(0), len(z) - 1)]
    return lo, hi


def aggregate(nll: np.ndarray, colour: np.ndarray, radius: int, sigma: float) -> np.ndarray:
    """The evidence of each tile (hypotheses, nph, npw) joined with its
    neighbours' within ``radius`` tiles, each weighted by how alike the
    tiles' mean colours are (log RGB distance, scale ``sigma``): a depth
    edge is most often a colour edge too, so the weights keep them apart."""
    logc = np.log(np.maximum(colour, 1e-4))
    nh, h, w = nll.shape
    pad = np.pad(nll, ((0, 0), (radius, radius), (radius, radius)), mode="edge")
    padc = np.pad(logc, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    out = np.zeros_like(nll)
    total = np.zeros((h, w))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            c = padc[radius + dy:radius + dy + h, radius + dx:radius + dx + w]
            wgt = np.exp(-((c - logc) ** 2).sum(-1) / (2 * sigma ** 2))
            out += wgt * pad[:, radius + dy:radius + dy + h, radius + dx:radius + dx + w]
            total += wgt
    return out / total


def _profile(spectra, K, options, sel) -> np.ndarray:
    """The profiled NLL of windows ``sel`` (indices) under ``K`` (all windows'), in chunks on the pool."""
    from ..parallel import thread_pool, workers
    steps = np.asarray(options.amplitude_steps, float)
    chunks = [c for c in np.array_split(sel, workers()) if len(c)]
    parts = thread_pool().map(lambda c: spectra.rows(c).profile_nll(K[c], options.colour_residual,
                                                                    options.model_error, steps), chunks)
    return np.concatenate(list(parts)) if chunks else np.empty(0)


def _hypothesis_nll(spectra, transfer, n: int, options, progress) -> np.ndarray:
    """NLL (n hypotheses, windows): every other hypothesis (and the last,
    infinity) for every window; each one between them only for the windows
    whose best so far is a neighbour of it, elsewhere the mean of its
    neighbours' (far from the best: no posterior mass either way).
    ``transfer(i)``: the transfer functions of hypothesis i."""
    m = len(spectra.a0)
    coarse = list(range(0, n, 2)) + ([n - 1] if (n - 1) % 2 else [])
    nll = np.full((n, m), np.nan)
    everyone = np.arange(m)
    for done, i in enumerate(coarse):
        nll[i] = _profile(spectra, transfer(i), options, everyone)
        if progress is not None:
            progress(done + 1, n)
    best = np.asarray(coarse)[np.argmin(nll[coarse], 0)]
    for done, i in enumerate(sorted(set(range(n)) - set(coarse))):
        sel = np.nonzero(np.abs(best - i) <= 1)[0]
        if len(sel):
            nll[i, sel] = _profile(spectra, transfer(i), options, sel)
        rest = np.isnan(nll[i])
        nll[i, rest] = 0.5 * (nll[i - 1, rest] + nll[i + 1, rest])
        if progress is not None:
            progress(len(coarse) + done + 1, n)
    return nll


def estimate_depth(capture, library, geometry, options: DepthFromBlurOptions | None = None, *, noise=None,
                   progress=None, refine=None) -> DepthEstimate:
    """Depth of ``capture`` (H, W, 3) float32 linear, taken through the lens
    of ``library`` (its PSFs at the capture's pixel pitch) at ``geometry``
    (``render.geometry.ImageGeometry``: the capture on the lens's sensor).
    ``noise``: the sensor's ``correct.NoiseModel`` (None: estimated from the
    capture). ``progress(done, total)``: called per depth hypothesis.
    ``refine``: a learned refinement, (``tile_features`` (C, nph, npw), the
    hypotheses' depths m) -> log depth (nph, npw) metres (None: the
    evidence alone)."""
    from ..correct.noise import estimate_noise
    from ..render.psfmap import psf_map

    options = options or DepthFromBlurOptions()
    img = check_capture(capture)
    h, w = img.shape[:2]
    if (geometry.height, geometry.width) != (h, w):
        raise InputRangeError("geometry", (geometry.height, geometry.width), f"({h}, {w}), the capture's size")
    t0 = time.perf_counter()
    noise = noise if noise is not None else estimate_noise(img)
    s, size = options.tile, options.window
    blocks = evidence.bins(size, options.max_frequency)
    index = evidence.block_index(size, blocks[0])
    spectra = evidence.WindowSpectra(img, s, size, blocks, noise, options.sharpness_px,
                                     slopes=options.texture_slopes)
    (nph, npw), clipped = spectra.tiles, spectra.clipped
    t_spectra = time.perf_counter() - t0

    grid = library.grid
    idx = np.arange(0, len(grid.diopters), options.hypothesis_step)
    if idx[-1] != len(grid.diopters) - 1:
        idx = np.append(idx, len(grid.diopters) - 1)          # infinity is always a hypothesis
    depths = grid.depths_m[idx]
    library.ensure(bins=idx)
    t_kernels = [0.0]
    camera_blur = np.zeros((len(depths), nph, npw))

    def transfer(i):
        t = time.perf_counter()
        # one kernel for each share x share tiles: a PSF changes little over a few tiles
        m = s * options.kernel_share
        pm = psf_map(library, geometry, np.full((h, w), depths[i]), m, clamp_field=True)
        K = evidence.otfs(pm.kernels, size, index)                          # (kph, kpw, 3, B)
        blur = blur_diameter_px(pm.kernels)
        camera_blur[i] = np.repeat(np.repeat(blur, options.kernel_share, 0), options.kernel_share, 1)[:nph, :npw]
        K = np.repeat(np.repeat(K, options.kernel_share, 0), options.kernel_share, 1)[:nph, :npw]
        K = K.reshape((-1,) + K.shape[2:])
        t_kernels[0] += time.perf_counter() - t
        return K

    nll = _hypothesis_nll(spectra, transfer, len(depths), options, progress)
    for i in np.nonzero(~camera_blur.any(axis=(1, 2)))[0]:
        # a hypothesis no window needed (between two that were): its blur between theirs
        camera_blur[i] = 0.5 * (camera_blur[max(i - 1, 0)] + camera_blur[min(i + 1, len(depths) - 1)])
    if options.aggregate > 0:
        nll = aggregate(nll.reshape(len(depths), nph, npw), spectra.mean.reshape(nph, npw, 3), options.aggregate,
                        options.aggregate_colour).reshape(len(depths), -1)
    t_kernels = t_kernels[0]
    est, conf, post = _posterior(nll, np.minimum(depths, grid.far_m), options.temperature, options.tolerance)
    conf = np.where(~np.isfinite(nll).all(0) | clipped, 0.0, conf)
    features = tile_features(post, est, conf, spectra, geometry, s)
    if refine is not None:
        # a learned refinement of the tiles' depths from their evidence (models.runtime.dfd_refine)
        if hasattr(refine, "check"):
            refine.check(len(features), s, len(depths))
        est = np.clip(np.exp(np.asarray(refine(features, depths), np.float64).reshape(-1)), grid.near_m, grid.far_m)
        if options.refine_within is not None:
            # the refinement moves a tile only within what its blur allows: the posterior's credible interval
            lo, hi = _quantiles(post, np.minimum(depths, grid.far_m), options.refine_within)
            est = np.clip(est, lo, hi)
    tile_d, fill_weight = (1.0 / est).reshape(nph, npw), conf.reshape(nph, npw)
    # the calibrated posterior and confidence, of the estimate as it stands (refined or not)
    hyp = np.minimum(depths, grid.far_m)
    post_c = post ** (options.temperature / options.confidence_temperature)
    post_c /= post_c.sum(0)
    conf_c = (post_c * (np.abs(hyp[:, None] - est) <= options.tolerance * est)).sum(0)
    conf_c = np.where(~np.isfinite(nll).all(0) | clipped, 0.0, conf_c)
    tile_c = conf_c.reshape(nph, npw)
    # the posterior's expected relative error of the estimate: what a user of the depth risks
    expected = (post_c * np.abs(hyp[:, None] - est) / est).sum(0)
    t_evidence = time.perf_counter() - t0 - t_spectra

    filled = fill.spread(tile_d, fill_weight)
    if options.fill == "bilateral":
        colours = fill.tile_colours(img, s, (nph, npw))
        pixel_d = fill.joint_bilateral(filled, fill_weight, colours, img, s, 2, options.fill_colour)
    else:
        r = options.fill_radius or s
        pixel_d = fill.guided(fill.luminance_guide(img), fill.upsample(filled, s, (h, w)), r, options.fill_eps)
    pixel_c = np.clip(fill.upsample(tile_c, s, (h, w)), 0.0, 1.0)
    near, far = grid.near_m, grid.far_m
    pixel_d = np.clip(np.nan_to_num(pixel_d, nan=1.0 / far), 1.0 / far, 1.0 / near)
    depth = (1.0 / pixel_d).astype(np.float32)
    seconds = {"spectra": t_spectra, "kernels": t_kernels, "evidence": t_evidence - t_kernels,
               "fill": time.perf_counter() - t0 - t_spectra - t_evidence}
    info = {"hypotheses_m": [float(x) for x in depths], "tiles": [nph, npw], "tile_px": s, "window_px": size,
            "noise": {"gain": noise.gain, "floor": noise.floor}, "seconds": seconds,
            "confident_share": float((tile_c >= 0.5).mean()), "expected_abs_rel": float(expected.mean()),
            "mean_confidence": float(tile_c.mean())}
    posterior = TilePosterior(hyp, post_c.reshape(len(depths), nph, npw),
                              est.reshape(nph, npw), camera_blur, s)
    return DepthEstimate(depth, pixel_c.astype(np.float32), tile_d, tile_c, info, features, posterior)
