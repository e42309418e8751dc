"""The correction jobs: undo a lens's blur on a capture (:func:`correct`),
and the DCDI chain, a capture given another lens's depth of field
(:func:`dof`). The rule that picks the deconvolution or the network
(``pipeline.choose_correction``), the capture's recorded geometry as
defaults, the fallbacks and the notes for the user are decided here, for the
`dcdi` command and the Blender add-on alike.

Units: depths in metres, pixel pitch in mm on the sensor, positions in
pixels (row, col).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputRangeError
from ..render.request import RenderRequest
from .control import Control
from .records import recorded_defaults
from .render import BokehRequest, BokehResult, _array
from .render import bokeh as run_bokeh
from .sources import PSFRequest


@dataclass(frozen=True)
class CorrectRequest:
    """Undo the blur of ``lens`` on ``capture`` (H, W, 3) float32 linear with
    its depth ``depth_m`` (H, W) metres (None: the deconvolution's
    ``one_depth_m`` everywhere).

    ``method``: 'auto' (the rule of ``pipeline.choose_correction``),
    'deconv' (the lens's own PSFs, any lens) or 'dacn' (a network: ``model``,
    a DACN file or run folder, else the lens's shipped one). ``lens`` None:
    only a given network, on a capture spanning its sensor. ``render``: the
    capture on the lens's sensor (pixel pitch, axis) and the PSF settings
    (their focus: where the sensor was; ``render.request.RenderRequest``;
    None: the capture spans the sensor's diagonal). ``deconv``: the
    deconvolution's ``correct.DeconvOptions`` (None: its defaults; given,
    refused where a network corrects). ``psf``: its PSFs. ``tile`` /
    ``overlap`` px, ``weights`` ('ema' or 'model'), ``device``: the
    network's. ``recorded``: what the capture file remembers
    (``io.capture_record.CaptureRecord``): its pixel pitch, axis and focus
    are the defaults of ``render``; a lens other than its own is refused."""

    capture: np.ndarray | None
    depth_m: np.ndarray | None
    lens: object
    method: str = "auto"
    model: str | Path | None = None
    render: RenderRequest | None = None
    deconv: object = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    tile: int = 256
    overlap: int = 32
    weights: str = "ema"
    device: str = "cpu"
    recorded: object = None
    image_name: str = "the capture"


@dataclass
class CorrectResult:
    """``image``: the sharp estimate (H, W, 3) float32 on the capture's grid;
    ``method`` ('deconv', 'dacn' or 'none') and ``reason``; ``geometry``: the
    capture on the lens's sensor (None without a lens); ``info``: the
    correction's own figures (PSF source and its message for a
    deconvolution); ``notes``: lines for the user; ``seconds``."""

    image: np.ndarray
    method: str
    reason: str
    geometry: object
    info: dict
    notes: list
    seconds: dict

    def as_dict(self) -> dict:
        return {"method": self.method, "reason": self.reason, **{k: v for k, v in self.info.items() if k != "method"}}


def with_recorded(request: CorrectRequest, shape=None) -> tuple[CorrectRequest, list]:
    """(``request`` with the capture's recorded geometry as its defaults,
    notes): ``records.recorded_defaults`` for a capture of ``shape`` (H, W)."""
    if request.recorded is None or request.lens is None:
        return request, []
    render, notes = recorded_defaults(request.render, request.lens, request.recorded, shape, request.image_name)
    return replace(request, render=render), notes


def _torch_importable() -> bool:
    import importlib.util
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):
        return False


def choose(request: CorrectRequest, pitch_mm: float | None) -> tuple[str, str]:
    """('deconv' or 'dacn', why): ``pipeline.choose_correction``'s rule, and
    where 'auto' picks a network and no PyTorch imports here, the
    deconvolution (auto never fails for want of torch)."""
    from ..pipeline import choose_correction
    lens_id = request.lens.id if request.lens is not None else None
    chosen, reason = choose_correction(lens_id, pitch_mm, request.method, request.model)
    if chosen == "dacn" and request.method == "auto" and not _torch_importable():
        if request.lens is not None:
            return "deconv", f"{reason}; but this Python has no PyTorch for it"
    return chosen, reason


def prepare(request: CorrectRequest, shape, *, networks=None):
    """The correction of a capture of ``shape`` (H, W): (the request with
    its recorded defaults, a ``pipeline.Deconvolution`` or
    ``NetworkCorrection``, the capture's geometry, notes on the record). ``networks(path, weights,
    device)`` loads a DACN, (model, info) (default:
    ``models.dacn.correct.load_dacn``; the add-on keeps the last one)."""
    from ..pipeline import Deconvolution, NetworkCorrection, check_correction, check_trained_for
    from ..models.registry import NETWORKS
    request, notes = with_recorded(request, shape)
    lens = request.lens
    check_correction(lens.id if lens is not None else None, request.method, request.model)
    h, w = shape
    geometry, settings = None, None
    if lens is not None:
        render = request.render or RenderRequest(lens)
        plan = render.plan(h, w, image=request.image_name)
        geometry, settings = plan.geometry, plan.settings
    chosen, reason = choose(request, geometry.pixel_pitch_mm if geometry is not None else None)
    if chosen == "dacn" and request.deconv is not None:
        raise InputRangeError("deconv", request.deconv,
                              f"only with the deconvolution; the network corrects here ({reason}): choose the "
                              "deconvolution (method deconv)")
    psf = request.psf
    render = request.render or (RenderRequest(lens) if lens is not None else None)
    deconv = request.deconv
    recorded_noise = getattr(request.recorded, "noise", None)
    if chosen == "deconv" and recorded_noise and getattr(deconv, "noise", None) is None:
        # the capture's own sensor model weighs the deconvolution's prior better than one estimated from it
        from ..correct import DeconvOptions, NoiseModel
        noise = NoiseModel.sensor(recorded_noise["full_well_electrons"], recorded_noise["read_noise_electrons"])
        deconv = replace(deconv or DeconvOptions(), noise=noise)
    template = None if lens is None else Deconvolution(
        lens, options=deconv, psf_source=psf.source, olf_file=psf.olf_file, basis_file=psf.basis_file,
        settings=settings, kernel_size=None if render.fit_kernel else settings.kernel_size,
        response=psf.response, geometry=geometry, reason=reason)
    if chosen == "deconv":
        return request, template, geometry, notes
    path = request.model if request.model is not None else NETWORKS["dacn"].shipped_file(lens.id)
    if networks is None:
        from ..models.dacn.correct import load_dacn

        def networks(p, weights, device):
            return load_dacn(p, weights=weights, device=device)
    model, info = networks(path, request.weights, request.device)
    check_trained_for(info, lens.id if lens is not None else None, path)
    return request, NetworkCorrection(model, info, request.tile, request.overlap, reason, deconvolution=template,
                                      geometry=geometry), geometry, notes


def correct(request: CorrectRequest, control: Control | None = None, *, networks=None) -> CorrectResult:
    """Run a :class:`CorrectRequest` (progress: 'PSFs' then 'deconvolving'
    windows, or 'correcting' tiles; cancel between them)."""
    from ..pipeline import pitch_note, recover
    control = control or Control()
    capture = _array("capture", request.capture, 3)
    request, correction, geometry, notes = prepare(request, capture.shape[:2], networks=networks)
    depth = request.depth_m
    if depth is None:
        one = getattr(request.deconv, "one_depth_m", None)
        if one is None:
            raise InputRangeError("depth_m", None, "the scene's depth map (H, W) metres, or one depth for the "
                                  "deconvolution's depth-unaware baseline (one_depth_m)")
        depth = np.full(capture.shape[:2], one, np.float32)
    depth = _array("depth_m", depth, 2)
    if depth.shape != capture.shape[:2]:
        raise InputRangeError("depth_m", depth.shape, f"{capture.shape[:2]}, the capture's size")
    from ..psf.library import LibraryGrid
    from ..render.inputs import depth_counts, depth_notes
    counts = depth_counts(depth, LibraryGrid().near_m)
    notes = notes + depth_notes(counts, f"the depth map of {request.image_name}",
                                "each takes its patch's depth, a patch with none is left as captured")
    if correction.method == "dacn":
        trained = (correction.info.get("meta") or {}).get("pixel_pitch_mm")
        note = pitch_note(trained, geometry.pixel_pitch_mm, "the correction network") if geometry else None
        if note:
            notes.append(note)
    control.say(f"correction by {'the network (DACN)' if correction.method == 'dacn' else 'the deconvolution'}: "
                f"{correction.reason}")
    stage = "correcting" if correction.method == "dacn" else "deconvolving"
    control.report(stage, 0, 1)
    t0 = time.perf_counter()
    image, info = recover(capture, depth, correction, control.counter(stage), psf_progress=control.counter("PSFs"))
    info = {**info, **counts}
    seconds = {"correction": time.perf_counter() - t0}
    return CorrectResult(image, correction.method, correction.reason, geometry, info, notes, seconds)


# ------------------------------------------------------------------ dof
@dataclass(frozen=True)
class DofRequest:
    """The DCDI chain: ``correct`` (a :class:`CorrectRequest` of the capture;
    its ``lens`` None: a sharp image, no correction; its ``depth_m`` None:
    the depth is ``estimator``'s) then ``bokeh`` (a :class:`BokehRequest`
    of the target lens, its image and depth filled here: the corrected
    image and the depth used). ``estimator``: a
    ``models.depth.estimators.DepthEstimator``, or None with a depth map."""

    correct: CorrectRequest
    bokeh: BokehRequest
    estimator: object = None


@dataclass
class DofResult:
    """``image``: the target lens's depth of field (H, W, 3) float32;
    ``corrected``: the all-in-focus estimate (the capture for a sharp
    image); ``depth_m`` and ``depth_source`` ('given' or the estimator's
    name); ``correction``: the :class:`CorrectResult` (None for a sharp
    image); ``bokeh``: the :class:`BokehResult`; ``notes``; ``seconds`` per
    stage."""

    image: np.ndarray
    corrected: np.ndarray
    depth_m: np.ndarray
    depth_source: str
    correction: CorrectResult | None
    bokeh: BokehResult
    notes: list
    seconds: dict

    def correction_dict(self) -> dict:
        if self.correction is None:
            return {"method": "none", "reason": "a sharp input: no correction"}
        return self.correction.as_dict()


def _depth(capture, request: DofRequest, seconds: dict) -> tuple[np.ndarray, str]:
    depth = request.correct.depth_m
    if depth is not None:
        depth = _array("depth_m", depth, 2)
        if depth.shape != capture.shape[:2]:
            raise InputRangeError("depth_m", depth.shape, f"{capture.shape[:2]}, the capture's size")
        return depth, "given"
    from ..models.depth.estimators import DepthEstimator
    from ..models.errors import ModelError
    if not isinstance(request.estimator, DepthEstimator):
        raise ModelError("no depth map and no depth estimator: give a depth map, or an estimator "
                         "(the shipped depth network of the camera lens, or a public one from a checkpoint)")
    t0 = time.perf_counter()
    depth = request.estimator.estimate(capture)
    seconds["depth"] = time.perf_counter() - t0
    return depth, request.estimator.name


def dof(request: DofRequest, control: Control | None = None, *, networks=None, cache=None) -> DofResult:
    """Run a :class:`DofRequest`: depth (given or estimated), correction,
    then the target lens's bokeh (module docstring)."""
    control = control or Control()
    capture = _array("capture", request.correct.capture, 3)
    seconds, notes = {}, []
    depth, depth_source = _depth(capture, request, seconds)
    corrected, fixed = capture, None
    if request.correct.lens is not None:
        fixed = correct(replace(request.correct, capture=capture, depth_m=depth), control, networks=networks)
        corrected = fixed.image
        seconds.update(fixed.seconds)
        notes += fixed.notes
    t0 = time.perf_counter()
    b = run_bokeh(replace(request.bokeh, image=corrected, depth_m=depth), control, cache=cache)
    seconds["psfs and bokeh"] = time.perf_counter() - t0
    notes = list(dict.fromkeys(notes + b.notes))         # the depth's notes once, not per stage
    return DofResult(b.image, corrected, depth, depth_source, fixed, b, notes, seconds)
