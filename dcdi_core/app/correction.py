"""The correction job: undo a lens's blur on a capture (:func:`correct`).
The DCDI chain that uses it (depth -> correction -> another lens's depth of
field) is ``app.pipeline``. The rule that picks the deconvolution or the network
(``app.correction_rule.choose_correction``), the capture's recorded geometry as
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
from ..control import Control
from .frame import capture_frame
from .render import _array
from ..psf.sources import PSFRequest


@dataclass(frozen=True)
class CorrectRequest:
    """Undo the blur of ``lens`` on ``capture`` (H, W, 3) float32 linear with
    its depth ``depth_m`` (H, W) metres (None: the deconvolution's
    ``one_depth_m`` everywhere).

    ``method``: 'auto' (the rule of ``app.correction_rule.choose_correction``),
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
    are the defaults of ``render``; a lens other than its own is refused.
    ``frame``: the capture's ``app.frame.CaptureFrame`` where the job made it
    already (``dof``: one frame for the depth and the correction); None:
    made here from ``lens``, ``render`` and ``recorded``. A correction that
    cannot run whatever the image (``app.correction_rule.check_correction``)
    is refused when the request is made: a front end makes it (``capture``
    None) before it reads an image."""

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
    frame: object = None

    def __post_init__(self):
        # what cannot run whatever the image is refused when the request is made, before any work
        # (no lens and no network: a sharp image in a dof job; `correct` refuses it when it chooses)
        if self.checked:
            from .correction_rule import check_correction
            check_correction(getattr(self.lens, "id", None), self.method, self.model)

    @property
    def checked(self) -> bool:
        """Whether the request checked its correction when made (it names a lens or a network)."""
        return self.lens is not None or self.model is not None


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


def frame_of(request: CorrectRequest, shape):
    """The capture's frame (``app.frame.CaptureFrame``): the request's own
    where it serves this lens and ``shape`` (H, W), else made here; None
    without a lens."""
    if request.lens is None:
        return None
    if request.frame is not None and request.frame.serves(request.lens, shape):
        return request.frame
    return capture_frame(request.lens, request.render, request.recorded, shape, request.image_name)


def _torch_importable() -> bool:
    import importlib.util
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):
        return False


def choose(request: CorrectRequest, pitch_mm: float | None) -> tuple[str, str]:
    """('deconv' or 'dacn', why): ``app.correction_rule.choose_correction``'s rule, and
    where 'auto' picks a network and no PyTorch imports here, the
    deconvolution (auto never fails for want of torch)."""
    from .correction_rule import choose_correction
    lens_id = request.lens.id if request.lens is not None else None
    chosen, reason = choose_correction(lens_id, pitch_mm, request.method, request.model,
                                       checked=request.checked)
    if chosen == "dacn" and request.method == "auto" and not _torch_importable():
        if request.lens is not None:
            return "deconv", f"{reason}; but this Python has no PyTorch for it"
    return chosen, reason


def prepare(request: CorrectRequest, shape, *, networks=None, sources=None):
    """The correction of a capture of ``shape`` (H, W): (the request with
    its frame and recorded defaults, a ``app.correction_rule.Deconvolution`` or
    ``NetworkCorrection``, the capture's geometry, notes on the record). ``networks(path, weights,
    device)`` loads a DACN, (model, info) (default:
    ``models.dacn.correct.load_dacn``; the add-on keeps the last one)."""
    from .correction_rule import Deconvolution, NetworkCorrection, check_trained_for
    from ..shipped import NETWORKS
    frame = frame_of(request, shape)
    notes = [] if frame is None else list(frame.notes)
    if frame is not None:
        request = replace(request, render=frame.render, frame=frame)
    lens = request.lens
    geometry = None if frame is None else frame.geometry
    settings = None if frame is None else frame.plan.settings
    # the rule checks the request (check_correction) before it chooses
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
        lens, options=deconv, geometry=geometry, reason=reason, sources=sources,
        psf=replace(psf, settings=settings, kernel_size=None if render.fit_kernel else settings.kernel_size))
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


def correct(request: CorrectRequest, control: Control | None = None, *, networks=None,
            sources=None) -> CorrectResult:
    """Run a :class:`CorrectRequest` (progress: 'PSFs' then 'deconvolving'
    windows, or 'correcting' tiles; cancel between them). ``sources`` as
    :func:`prepare`'s."""
    from .correction_rule import pitch_note, recover
    control = control or Control()
    capture = _array("capture", request.capture, 3)
    request, correction, geometry, notes = prepare(request, capture.shape[:2], networks=networks, sources=sources)
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
