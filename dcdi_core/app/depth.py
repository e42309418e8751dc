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
    capture); ``recorded``: what the capture file remembers."""

    capture: np.ndarray
    lens: object
    render: object = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    options: object = None
    noise: object = None
    recorded: object = None
    image_name: str = "the capture"


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
    est = estimate_depth(capture, src.library, plan.geometry, request.options, noise=noise,
                         progress=control.counter("depth hypotheses"))
    info = {**est.info, "psf_source": src.kind, "noise_from": "given" if request.noise is not None else
            "the capture's record" if recorded_noise else "estimated from the capture"}
    share = info["confident_share"]
    if share < 0.25:
        notes = notes + [f"only {share:.0%} of {request.image_name}'s tiles have a confident depth (texture above "
                         "the noise): the rest is filled from them; check the confidence map"]
    seconds = {"psfs": t_psf, **est.info["seconds"]}
    return DepthResult(est.depth_m, est.confidence, plan.geometry, info, notes, seconds)
