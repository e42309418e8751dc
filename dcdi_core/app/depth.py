"""The depth job: metric depth of a capture from its own lens's blur
(``dfd.estimate_depth``), with the capture's recorded geometry (pixel pitch,
axis, focus) as defaults, for the `dcdi` command and the add-on alike.

Units: depths in metres, pixel pitch in mm on the sensor.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..control import Control
from ..io.npzfile import FileCache
from ..models.depth.estimators import DepthEstimator
from ..models.runtime.dfd_refine import DfdRefiner
from .frame import capture_frame
from .render import _array
from ..psf.sources import PSFRequest


@dataclass(frozen=True)
class DepthRequest:
    """Estimate the depth of ``capture`` (H, W, 3) float32 linear, taken
    through ``lens``. ``render``: the capture on the lens's sensor
    (``render.request.RenderRequest``; None: the lens's defaults or what
    ``recorded`` says); ``psf``: its PSFs; ``options``: the estimator's
    ``dfd.DepthFromBlurOptions`` (None: defaults); ``noise``: the sensor's
    ``correct.NoiseModel`` (None: the record's, else estimated from the
    capture); ``recorded``: what the capture file remembers. ``refine``:
    the learned refinement of the tiles' depths ('auto': the lens's shipped
    one where the capture has the pixel pitch it learned; None: the evidence
    alone; a path: that file). ``frame``: the capture's
    ``app.frame.CaptureFrame`` where the job made it already (None: made
    here from ``lens``, ``render`` and ``recorded``)."""

    capture: np.ndarray
    lens: object
    render: object = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    options: object = None
    noise: object = None
    recorded: object = None
    image_name: str = "the capture"
    refine: object = "auto"
    frame: object = None


@dataclass
class DepthResult:
    """``depth_m`` (H, W) float32 metres within the PSF library's depth
    range, ``confidence`` (H, W) float32 in [0, 1], the capture's
    ``geometry``, the estimator's ``info``, ``notes`` for the user and
    ``seconds``."""

    depth_m: np.ndarray
    confidence: np.ndarray
    geometry: object
    info: dict
    notes: list
    seconds: dict
    posterior: object = None      # dfd.TilePosterior: the tiles' evidence, for app.dof's rule


def recorded_better(lens_id: str, pitch_mm: float) -> bool:
    """Whether the depth from blur of ``lens_id`` at ``pitch_mm`` is recorded
    30 % better than a constant depth on held-out captures: the registry
    (``shipped.REFINEMENT.beats_constant_depth``) says so for the lens and its
    shipped refinement learned this pitch (the record is the refined estimator's)."""
    from ..shipped import REFINEMENT
    if lens_id not in REFINEMENT.beats_constant_depth:
        return False
    refiner, _ = refinement("auto", lens_id, pitch_mm)
    return refiner is not None


# a refinement file is read once for a job's checks and its estimate (and kept
# for the next job while the file is unchanged on disk)
_open_refiner = FileCache(DfdRefiner, 2, "depth refinements")


def refinement(refine, lens_id: str, pitch_mm: float):
    """(a ``models.runtime.dfd_refine.DfdRefiner`` or None, a note or ''):
    ``refine`` 'auto' takes the lens's shipped one where the capture has the
    pixel pitch it learned (elsewhere its learned scene statistics do not
    hold: the evidence alone, said in the note); a path is run as given."""
    if refine is None or refine is False:
        return None, ""
    from ..psf.pitch import REFINEMENT_PITCH_RTOL, learned_pitch_holds
    from ..shipped import REFINEMENT
    path = REFINEMENT.shipped_file(lens_id) if refine == "auto" else refine
    if path is None:
        return None, ""
    refiner = _open_refiner(path)
    refiner.check_lens(lens_id)
    learned = refiner.meta.get("pixel_pitch_mm")
    if refine == "auto" and learned and not learned_pitch_holds(pitch_mm, learned, REFINEMENT_PITCH_RTOL):
        return None, (f"the depth is the evidence of the blur alone: the learned refinement of {lens_id} learned "
                      f"{learned * 1000:.4g} um pixels and the capture has {pitch_mm * 1000:.4g} um")
    return refiner, ""


def estimate(request: DepthRequest, control: Control | None = None, *, sources=None) -> DepthResult:
    """Run a :class:`DepthRequest` (progress: 'PSFs', then 'depth
    hypotheses'). ``sources``: the job's ``app.sources.SourceCache`` (the
    lens's PSF source kept for the correction that follows; None: opened
    for this estimate alone)."""
    from ..correct.noise import NoiseModel
    from ..dfd import estimate_depth
    from ..psf.sources import open_source

    control = control or Control()
    capture = _array("capture", request.capture, 3)
    shape = capture.shape[:2]
    frame = request.frame
    if frame is None or not frame.serves(request.lens, shape):
        frame = capture_frame(request.lens, request.render, request.recorded, shape, request.image_name)
    plan, notes = frame.plan, list(frame.notes)
    noise = request.noise
    recorded_noise = getattr(request.recorded, "noise", None)
    if noise is None and recorded_noise:
        noise = NoiseModel.sensor(recorded_noise["full_well_electrons"], recorded_noise["read_noise_electrons"])
    t0 = time.perf_counter()
    psf = request.psf if request.psf.settings is not None else replace(request.psf, settings=plan.settings)
    src = (sources.open if sources is not None else open_source)(request.lens, plan.geometry, psf, control=control)
    t_psf = time.perf_counter() - t0
    refiner, why = refinement(request.refine, request.lens.id, plan.geometry.pixel_pitch_mm)
    if why:
        notes = notes + [why]
    est = estimate_depth(capture, src.library, plan.geometry, request.options, noise=noise,
                         progress=control.counter("depth hypotheses"), refine=refiner)
    info = {**est.info, "refined": None if refiner is None else str(refiner.path), "psf_source": src.kind, "noise_from": "given" if request.noise is not None else
            "the capture's record" if recorded_noise else "estimated from the capture"}
    share = info["confident_share"]
    if share < 0.25:
        notes = notes + [f"only {share:.0%} of {request.image_name}'s tiles have a confident depth (texture above "
                         "the noise): the rest is filled from them; check the confidence map"]
    seconds = {"psfs": t_psf, **est.info["seconds"]}
    return DepthResult(est.depth_m, est.confidence, plan.geometry, info, notes, seconds, est.posterior)


def target_blur(lens, pixel_pitch_mm: float, focus_m=None, keep=None):
    """The target lens's thin-lens defocus blur diameter (px) as a function
    of depth (m, array): ``keep`` (near, far) metres kept sharp, else
    focused at ``focus_m`` (metres, inf; None or 'prescribed': as its
    prescription stands)."""
    from ..optics.paraxial import prescribed_focus_diopters
    from ..psf.sampling import blur_px_per_diopter
    k = blur_px_per_diopter(lens, pixel_pitch_mm)
    if keep is not None:
        lo, hi = 1.0 / float(keep[1]), 1.0 / float(keep[0])
        return lambda z: k * np.maximum(np.maximum(lo - 1.0 / np.asarray(z), 1.0 / np.asarray(z) - hi), 0.0)
    if focus_m is None or isinstance(focus_m, str):
        f = prescribed_focus_diopters(lens)
    else:
        f = 0.0 if not np.isfinite(float(focus_m)) else 1.0 / float(focus_m)
    return lambda z: k * np.abs(1.0 / np.asarray(z, np.float64) - f)


@dataclass(frozen=True)
class DofDepthRule:
    """Where `dcdi dof` uses the correction when the depth is read from the
    capture's blur, and when it refuses.

    A wrong depth costs more after the correction than before it: the
    target lens then blurs a sharp image by the wrong amount, where the
    capture's own blur had hidden part of the error (measured: the demo's
    far board read at 2.2 m instead of 3-6 m). Per tile, the posterior over
    depth (``dfd.TilePosterior``) gives the expected error of the bokeh's
    blur with and without the correction, on a log scale (a natural
    texture's lost detail grows with the log of the blur ratio): the target
    lens's blur at the estimate (with ``residual_px`` of blur left by the
    correction, or the camera's blur at each hypothesis without it) against
    its blur at each hypothesis. ``neighbours``: the share of a tile's
    posterior taken from its 3 x 3 neighbourhood's (a pixel of a tile may
    lie on a neighbour's surface). The correction is kept where it is
    expected to bring the bokeh nearer (blended across a tile); below
    ``min_share`` of the frame the correction would do almost nothing, and
    `dcdi dof` asks for a depth map instead. Measured by `python -m lab
    dof-rule` (docs/depth.md)."""

    residual_px: float = 1.5
    floor_px: float = 1.0
    min_share: float = 0.2
    neighbours: float = 0.5

    def __post_init__(self):
        from ..errors import InputRangeError
        for name, lo, hi in (("residual_px", 0.0, 1e3), ("floor_px", 1e-3, 1e3), ("min_share", 0.0, 1.01),
                             ("neighbours", 0.0, 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or not lo <= v <= hi:
                raise InputRangeError(f"DofDepthRule.{name}", v, f"a number {lo:g} to {hi:g}")

    def gain(self, post, blur_of) -> np.ndarray:
        """(nph, npw): the expected log-blur error without the correction
        less that with it (> 0: the correction helps the bokeh there)."""
        # blur diameters add in quadrature, each at least a pixel (floor_px): nothing is sharper than that
        floor2 = self.floor_px ** 2
        bt = np.sqrt(blur_of(post.depths_m) ** 2 + floor2)[:, None, None]                    # the ideal's
        at2 = (blur_of(post.estimate_m) ** 2)[None] + floor2
        with_fix = np.abs(np.log(np.sqrt(at2 + self.residual_px ** 2) / bt))
        without = np.abs(np.log(np.sqrt(at2 + np.nan_to_num(post.camera_blur_px) ** 2) / bt))
        p = post.posterior
        if self.neighbours > 0:
            # a pixel of a tile may lie on a neighbour's surface (a depth edge, shapes smaller than a tile): its
            # posterior is partly its 3 x 3 neighbourhood's, so disagreeing neighbours make it less sure
            from ..dfd.fill import box
            p = (1.0 - self.neighbours) * p + self.neighbours * box(p, 1)
        return (p * (without - with_fix)).sum(0)

    def mask(self, post, blur_of, shape) -> np.ndarray:
        """(H, W) float32 in [0, 1]: the correction's weight at each pixel."""
        from ..dfd.fill import upsample
        keep = (self.gain(post, blur_of) > 0).astype(np.float64)
        return np.clip(upsample(keep, post.tile_px, shape), 0.0, 1.0).astype(np.float32)

    def verdict(self, share: float) -> str | None:
        """None where `dcdi dof` runs, else why it refuses (one clause)."""
        if share < self.min_share:
            return (f"the correction would help the bokeh on only {share:.0%} of the frame (it runs from "
                    f"{self.min_share:.0%})")
        return None


class BlurDepth(DepthEstimator):
    """The depth of a capture read from its own blur through ``lens``
    (:func:`estimate` with these settings: ``render``, ``psf``,
    ``recorded``, ``image_name``; ``frame``: the capture's
    ``app.frame.CaptureFrame``, made once by the job), as a
    ``models.depth.estimators.DepthEstimator`` (name 'blur')."""

    name = "blur"

    def __init__(self, lens, render=None, psf: PSFRequest | None = None, recorded=None,
                 image_name: str = "the capture", frame=None):
        self.request = DepthRequest(None, lens, render=render, psf=psf or PSFRequest(), recorded=recorded,
                                    image_name=image_name, frame=frame)

    def run(self, img, control: Control | None = None, sources=None) -> DepthResult:
        """The whole :class:`DepthResult` of ``img`` (its posterior:
        ``app.dof``'s rule); ``sources``: the job's ``app.sources.
        SourceCache``, whose camera PSFs the correction then shares."""
        return estimate(replace(self.request, capture=img), control, sources=sources)

    def _estimate(self, img):
        return self.run(img).depth_m


def blur_estimator(lens, render=None, psf: PSFRequest | None = None, recorded=None, image_name="the capture",
                   frame=None) -> BlurDepth:
    """A :class:`BlurDepth` of ``lens`` with these settings, for ``app.dof`` and the demo."""
    return BlurDepth(lens, render, psf, recorded, image_name, frame)


# what the refusals below offer where no depth is given
BLUR_HINT = "the depth from the capture's own blur (--depth-backend blur: numpy, no checkpoint; docs/depth.md)"


def dof_estimator(camera, correct_request, backend: str | None = None, checkpoint=None, threads: int | None = None):
    """The depth estimator of a DCDI job that has no depth map, by the rule
    (``backend`` None): the depth from the capture's blur where the registry
    records it better than a constant for ``camera`` at the capture's pitch
    (``correct_request.frame``), else the camera lens's shipped depth
    network where it beats a constant, else a ``ModelError`` asking for a
    depth map. A ``backend`` given ('blur', 'dcdi' or a public estimator's
    name, with ``checkpoint``) is loaded as asked. Loaded (and refused,
    by name) before any work; ``threads``: torch's, for a network."""
    from ..errors import ModelError
    from ..shipped import network

    lens_id = camera.id if camera is not None else None
    if backend is None:
        backend = "dcdi"
        if camera is not None and checkpoint is None and correct_request is not None:
            backend = "blur" if recorded_better(lens_id, correct_request.frame.pitch_mm) else "dcdi"
    if backend == "blur":
        if camera is None:
            raise ModelError("--depth-backend blur reads depth from the camera lens's blur: give --camera LENS "
                             "(--camera none: a sharp image has none), or --depth")
        r = correct_request
        return blur_estimator(camera, r.render, r.psf, r.recorded, r.image_name, frame=r.frame)
    ck = checkpoint
    if ck is None and backend == "dcdi":
        nets = network("depth")
        ck = nets.shipped_file(lens_id) if lens_id is not None else None
        if ck is None:
            raise ModelError("no depth map (--depth) and no shipped depth network for "
                             f"{'a sharp image (--camera none)' if camera is None else camera.id} (shipped: "
                             f"{', '.join(nets.shipped_keys()) or 'none'}); give --depth, {BLUR_HINT}, or "
                             "--depth-backend with --depth-checkpoint")
        if lens_id not in nets.beats_constant_depth:
            # a guess worse than one number for the whole frame would blur the wrong things: ask instead
            raise ModelError(f"no depth map (--depth): neither the shipped depth network of {lens_id} nor the "
                             "depth from its blur at this pixel pitch is recorded 30 % better than a constant depth "
                             "on held-out scenes; give --depth DEPTH.exr, or ask for an estimate: " + BLUR_HINT +
                             ", a public estimator (--depth-backend unidepth, depth-anything-v2 or depth-pro), "
                             "or your own network (--depth-checkpoint)")
    from ..models.depth.estimators import load_estimator
    if threads is not None:
        import torch
        torch.set_num_threads(int(threads))
    opts = {"threads": threads} if backend == "dcdi" and threads is not None else {}
    return load_estimator(backend, ck, **opts)
