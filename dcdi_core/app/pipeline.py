"""The DCDI pipeline: a capture given another lens's depth of field
(:func:`dof`): its depth (given, or estimated), the correction of its lens's
blur (``app.correction``), then the target lens's bokeh (``app.render``).
The capture's frame (``app.frame``) is made once and handed to the depth
estimate and the correction.

Units: depths in metres, pixel pitch in mm on the sensor, positions in
pixels (row, col).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ..control import Control
from ..errors import InputRangeError
from .correction import CorrectRequest, CorrectResult, correct
from .frame import capture_frame
from .render import BokehRequest, BokehResult, _array, bokeh_plan
from .render import bokeh as run_bokeh
from .sources import SourceCache


@dataclass(frozen=True)
class DofRequest:
    """The DCDI chain: ``correct`` (a :class:`CorrectRequest` of the capture;
    its ``lens`` None: a sharp image, no correction; its ``depth_m`` None:
    the depth is ``estimator``'s) then ``bokeh`` (a :class:`BokehRequest`
    of the target lens, its image and depth filled here: the corrected
    image and the depth used). ``estimator``: a
    ``models.depth.estimators.DepthEstimator``; None without a depth map:
    the rule's (``app.depth.dof_estimator``: ``depth_backend``, or by the
    rule where that is None; ``depth_checkpoint``; torch's ``threads``).
    The capture's frame is made here, once, where ``correct`` has none.
    ``uncertain_depth``: where the depth read from the capture's blur is
    too uncertain for the correction to help the bokeh on enough of the
    frame (``app.depth.DofDepthRule``), 'refuse' (a ``ModelError`` asking
    for a depth map, before the correction) or 'accept' (run, with a
    note). Either way the correction is kept only where the rule expects it
    to help."""

    correct: CorrectRequest
    bokeh: BokehRequest
    estimator: object = None
    uncertain_depth: str = "refuse"
    depth_backend: str | None = None
    depth_checkpoint: object = None
    threads: int | None = None

    def __post_init__(self):
        if self.uncertain_depth not in ("refuse", "accept"):
            raise InputRangeError("uncertain_depth", self.uncertain_depth, "'refuse' or 'accept'")


@dataclass
class DofResult:
    """``image``: the target lens's depth of field (H, W, 3) float32;
    ``corrected``: the all-in-focus estimate (the capture for a sharp
    image); ``depth_m`` and ``depth_source`` ('given' or the estimator's
    name); ``correction``: the :class:`CorrectResult` (None for a sharp
    image); ``bokeh``: the :class:`BokehResult`; ``notes``; ``seconds`` per
    stage; ``corrected_share``: where the depth was read from the blur, the
    share of the frame the correction was kept on, and ``depth``: that
    estimate's ``app.depth.DepthResult`` (its confidence, posterior and
    PSF source; else None)."""

    image: np.ndarray
    corrected: np.ndarray
    depth_m: np.ndarray
    depth_source: str
    correction: CorrectResult | None
    bokeh: BokehResult
    notes: list
    seconds: dict
    corrected_share: float | None = None   # the share of the frame the correction was kept on (a blur depth)
    depth: object = None                   # app.depth.DepthResult where the depth was read from the blur

    def correction_dict(self) -> dict:
        if self.correction is None:
            return {"method": "none", "reason": "a sharp input: no correction"}
        return self.correction.as_dict()


def _depth(capture, request: DofRequest, seconds: dict, control: Control, sources):
    """(depth (H, W) metres, its source's name, the depth estimate's
    ``app.depth.DepthResult`` where it was read from the capture's blur,
    else None)."""
    depth = request.correct.depth_m
    if depth is not None:
        depth = _array("depth_m", depth, 2)
        if depth.shape != capture.shape[:2]:
            raise InputRangeError("depth_m", depth.shape, f"{capture.shape[:2]}, the capture's size")
        return depth, "given", None
    from ..models.depth.estimators import DepthEstimator
    from ..errors import ModelError
    if not isinstance(request.estimator, DepthEstimator):
        raise ModelError("no depth map and no depth estimator: give a depth map, or an estimator "
                         "(the shipped depth network of the camera lens, or a public one from a checkpoint)")
    t0 = time.perf_counter()
    result = None
    from .depth import BlurDepth
    if isinstance(request.estimator, BlurDepth):
        # the depth from the capture's blur: its posterior for the rule, its PSF source for the correction
        # its progress and cancel are the job's; which PSFs serve is said once, by the correction that shares them
        result = request.estimator.run(capture, replace(control, note=None), sources)
        depth = result.depth_m
    else:
        depth = request.estimator.estimate(capture)
    seconds["depth"] = time.perf_counter() - t0
    return depth, request.estimator.name, result


def _correction_weight(request: DofRequest, shape, target_plan, estimated):
    """(the correction's weight (H, W) float32 in [0, 1], notes), or (None,
    []) where the depth was given or has no posterior: where the depth was
    read from the capture's blur, the correction is kept only where it is
    expected to bring the bokeh nearer (``app.depth.DofDepthRule``); where
    that is too little of the frame, refused ('refuse') or said ('accept')."""
    post = None if estimated is None else estimated.posterior
    if request.correct.depth_m is not None or post is None or request.correct.lens is None:
        return None, []
    from .depth import DofDepthRule, target_blur
    b = request.bokeh
    _, plan, _ = target_plan
    keep = b.keep
    blur_of = target_blur(b.lens, plan.geometry.pixel_pitch_mm, None if keep is not None else b.focus_m, keep)
    rule = DofDepthRule()
    weight = rule.mask(post, blur_of, shape)
    share = float(weight.mean())
    why = rule.verdict(share)
    notes = [f"the depth was read from the capture's blur: the correction is kept on {share:.0%} of the frame, "
             "where it is expected to bring the bokeh nearer the target lens's (elsewhere the capture as it is)"]
    if why is None:
        return weight, notes
    if request.uncertain_depth == "accept":
        return weight, notes + [f"the depth read from the capture's blur is too uncertain here ({why}): "
                                "a depth map would do more"]
    from ..errors import ModelError
    raise ModelError(f"the depth read from the capture's blur is too uncertain here: {why}. Give a depth map "
                     "(--depth DEPTH.exr: an RGB-D camera's or a metric estimator's), or run anyway with "
                     "--uncertain-depth accept")


def _decided(request: DofRequest, shape) -> DofRequest:
    """The job's decisions, made once: the capture's frame (for the depth
    and the correction) and, without a depth map or an estimator, the depth
    estimator by the rule."""
    c = request.correct
    if c.lens is not None and c.frame is None:
        c = replace(c, frame=capture_frame(c.lens, c.render, c.recorded, shape, c.image_name))
    estimator = request.estimator
    from .depth import BlurDepth
    if isinstance(estimator, BlurDepth) and estimator.request.frame is None and c.frame is not None \
            and estimator.request.lens is c.lens and estimator.request.render == c.render \
            and estimator.request.recorded is c.recorded:
        estimator = BlurDepth(c.lens, estimator.request.render, estimator.request.psf, estimator.request.recorded,
                              estimator.request.image_name, frame=c.frame)     # the job's one frame
    if estimator is None and c.depth_m is None:
        from .depth import dof_estimator
        estimator = dof_estimator(c.lens, c if c.lens is not None else None, request.depth_backend,
                                  request.depth_checkpoint, request.threads)
    return replace(request, correct=c, estimator=estimator)


def dof(request: DofRequest, control: Control | None = None, *, networks=None, cache=None) -> DofResult:
    """Run a :class:`DofRequest`: depth (given or estimated), correction,
    then the target lens's bokeh (module docstring). ``cache``: the front
    end's ``app.sources.SourceCache`` (None: one for this job), which holds
    each lens's PSF source once for the job."""
    control = control or Control()
    capture = _array("capture", request.correct.capture, 3)
    request = _decided(request, capture.shape[:2])
    target = bokeh_plan(request.bokeh, capture.shape[:2])           # the target lens's plan, once for the job
    seconds, notes = {}, []
    # the job's PSF sources: the camera lens's, shared by the depth from its blur and the correction, and the
    # target lens's (the front end's kept ones where it gives them)
    sources = cache if cache is not None else SourceCache()
    depth, depth_source, estimated = _depth(capture, request, seconds, control, sources)
    weight, notes = _correction_weight(request, capture.shape[:2], target, estimated)   # refused here, before the correction
    corrected, fixed = capture, None
    if request.correct.lens is not None:
        fixed = correct(replace(request.correct, capture=capture, depth_m=depth), control, networks=networks,
                        sources=sources)
        corrected = fixed.image
        if weight is not None:
            corrected = (weight[..., None] * corrected + (1.0 - weight[..., None]) * capture).astype(np.float32)
        seconds.update(fixed.seconds)
        notes += fixed.notes
    t0 = time.perf_counter()
    b = run_bokeh(replace(request.bokeh, image=corrected, depth_m=depth), control, cache=sources, plan=target)
    seconds["psfs and bokeh"] = time.perf_counter() - t0
    notes = list(dict.fromkeys(notes + b.notes))         # the depth's notes once, not per stage
    share = None if weight is None else float(weight.mean())
    return DofResult(b.image, corrected, depth, depth_source, fixed, b, notes, seconds, share, estimated)
