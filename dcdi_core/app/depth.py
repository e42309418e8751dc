"""The depth job: metric depth of a capture from its own lens's blur
(``dfd.estimate_depth``), with the capture's recorded geometry (pixel pitch,
axis, focus) as defaults, for the `dcdi` command and the add-on alike.

Units: depths in metres, pixel pitch in mm on the sensor.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from .control import Control
from .render import _array
from .sources import PSFRequest


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
    alone; a path: that file)."""

    capture: np.ndarray
    lens: object
    render: object = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    options: object = None
    noise: object = None
    recorded: object = None
    image_name: str = "the capture"
    refine: object = "auto"


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


def shipped_refinement(lens_id: str):
    """The shipped refinement file of ``lens_id`` (weights/dfd-refine-<lens>.npz), or None."""
    from ..models.registry import weights_file
    return weights_file("dfd-refine-", lens_id)


def capture_pitch_mm(lens, render, recorded, shape, image_name="the capture") -> float:
    """The pixel pitch (mm) of a capture of ``shape`` (H, W) through
    ``lens``: ``render``'s, else the record's, else spanning the sensor."""
    from ..render.request import RenderRequest
    from .records import recorded_defaults
    render, _ = recorded_defaults(render, lens, recorded, shape, image_name)
    return (render or RenderRequest(lens)).plan(*shape, image=image_name).geometry.pixel_pitch_mm


def recorded_better(lens_id: str, pitch_mm: float) -> bool:
    """Whether the depth from blur of ``lens_id`` at ``pitch_mm`` is recorded
    30 % better than a constant depth on held-out captures: the lens is in
    the registry's ``BLUR_DEPTH_BEATS_CONSTANT`` and its shipped refinement
    learned this pitch (the record is the refined estimator's)."""
    from ..models.registry import BLUR_DEPTH_BEATS_CONSTANT
    if lens_id not in BLUR_DEPTH_BEATS_CONSTANT:
        return False
    refiner, _ = refinement("auto", lens_id, pitch_mm)
    return refiner is not None


def refinement(refine, lens_id: str, pitch_mm: float):
    """(a ``models.runtime.dfd_refine.DfdRefiner`` or None, a note or ''):
    ``refine`` 'auto' takes the lens's shipped one where the capture has the
    pixel pitch it learned (elsewhere its learned scene statistics do not
    hold: the evidence alone, said in the note); a path is run as given."""
    if refine is None or refine is False:
        return None, ""
    from ..models.runtime.dfd_refine import DfdRefiner
    path = shipped_refinement(lens_id) if refine == "auto" else refine
    if path is None:
        return None, ""
    refiner = DfdRefiner(path)
    refiner.check_lens(lens_id)
    learned = refiner.meta.get("pixel_pitch_mm")
    if refine == "auto" and learned and abs(pitch_mm / learned - 1) > 0.01:
        return None, (f"the depth is the evidence of the blur alone: the learned refinement of {lens_id} learned "
                      f"{learned * 1000:.4g} um pixels and the capture has {pitch_mm * 1000:.4g} um")
    return refiner, ""


def estimate(request: DepthRequest, control: Control | None = None) -> DepthResult:
    """Run a :class:`DepthRequest` (progress: 'PSFs', then 'depth
    hypotheses')."""
    from ..correct.noise import NoiseModel
    from ..dfd import estimate_depth
    from ..render.request import RenderRequest
    from .records import recorded_defaults
    from .sources import open_source

    control = control or Control()
    capture = _array("capture", request.capture, 3)
    h, w = capture.shape[:2]
    render, notes = recorded_defaults(request.render, request.lens, request.recorded, (h, w), request.image_name)
    render = render or RenderRequest(request.lens)
    plan = render.plan(h, w, image=request.image_name)
    noise = request.noise
    recorded_noise = getattr(request.recorded, "noise", None)
    if noise is None and recorded_noise:
        noise = NoiseModel.sensor(recorded_noise["full_well_electrons"], recorded_noise["read_noise_electrons"])
    t0 = time.perf_counter()
    psf = request.psf if request.psf.settings is not None else replace(request.psf, settings=plan.settings)
    src = open_source(request.lens, plan.geometry, psf, control=control)
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
    return DepthResult(est.depth_m, est.confidence, plan.geometry, info, notes, seconds)


def blur_estimator(lens, render=None, psf: PSFRequest | None = None, recorded=None, image_name="the capture"):
    """A ``models.depth.estimators.DepthEstimator`` (name 'blur') that reads
    a capture's depth from its own blur through ``lens`` (:func:`estimate`
    with these settings), for ``app.dof`` and the demo."""
    from ..models.depth.estimators import DepthEstimator

    class BlurDepth(DepthEstimator):
        name = "blur"

        def _estimate(self, img):
            request = DepthRequest(img, lens, render=render, psf=psf or PSFRequest(), recorded=recorded,
                                   image_name=image_name)
            return estimate(request).depth_m

    return BlurDepth()
