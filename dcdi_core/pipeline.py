"""DCDI end to end: one minimalist-lens capture -> the depth of field of any lens.

The paper's I_A: recover the all-in-focus image I_R and the depth D_P (a
monocular estimator), then render a target lens's depth of field on them,
keeping a depth range sharp (or focusing), with that lens's PSFs from the
Omni-Lens-Field where it covers the request, else traced.

The stages, in the order the data need them (both corrections take the depth
map, so depth comes first; the paper estimates it on the aberrated capture
too):

1. depth: the given map, else the estimator's (``models.depth``);
2. correction of the camera lens's blur, by the one rule of
   :func:`choose_correction`: the deconvolution with the lens's own PSFs
   (``dcdi_core.correct``: any lens, no training) or the lens's shipped
   network (DACN) where that network is recorded better than the
   deconvolution and the image has the pixel pitch it learned (``camera``
   None: the image is already sharp and is passed on untouched);
3. PSFs and bokeh: ``render.simulate.bokeh`` of the target lens (the PSF
   source from ``runtime.library.psf_source``; only the depth bins the map
   touches are filled).

Nothing a scene does not need is computed: no estimator is loaded when a
depth map is given, no network when the deconvolution corrects or the
camera is 'none'.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np

from .errors import InputRangeError
from .models.errors import ModelError
from .models.registry import NETWORKS

PITCH_TOLERANCE = 0.05


def shipped_model(kind: str, lens_id: str) -> Path | None:
    """The shipped ``kind`` ('dacn' or 'depth') file for a lens, or None."""
    if kind not in ("dacn", "depth"):
        raise InputRangeError("shipped model kind", kind, "dacn or depth")
    return NETWORKS[kind].shipped_file(lens_id)


def shipped_lenses(kind: str) -> list[str]:
    return NETWORKS[kind].shipped_keys()


@dataclass
class DofResult:
    image: np.ndarray                   # (H, W, 3) linear: the target lens's depth of field
    corrected: np.ndarray               # the all-in-focus estimate I_R (the input itself for camera None)
    depth_m: np.ndarray                 # the depth used (given or estimated)
    depth_source: str                   # 'given' or the estimator's name
    psf_source: str                     # 'basis', 'olf' or 'trace'
    psf_message: str
    seconds: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    correction: dict = field(default_factory=dict)   # method, why, and the correction's own info


def pitch_note(trained_mm: float | None, image_mm: float, what: str) -> str | None:
    """A note when an image's pixel pitch is not the one a network learned."""
    if not trained_mm or abs(image_mm / trained_mm - 1) <= PITCH_TOLERANCE:
        return None
    return (f"{what} learned {trained_mm * 1000:.4g} um pixels, this image has {image_mm * 1000:.4g} um "
            f"({image_mm / trained_mm:.2f}x): its blur is {trained_mm / image_mm:.2f}x the size it was trained on")


# ------------------------------------------------------------------ which correction
METHODS = ("auto", "deconv", "dacn")

# the names a user knows the choice's inputs by: the `dcdi correct` options
# (`dcdi dof` passes its own, the add-on its panel's words); the PSF source's
# ('psf_source', 'basis', 'olf': ``runtime.library.PSF_SOURCE_LABELS``) may be
# given beside them
CORRECTION_LABELS = MappingProxyType({"method": "--method", "model": "--model", "lens": "--lens"})

REPORT = "the DACN study (docs/correction.md)"


def trained_pitch_mm(path) -> float | None:
    """The pixel pitch (mm) a DACN file (.npz) learned, from its metadata
    record alone (None: not recorded, or a run folder / checkpoint)."""
    path = Path(path)
    if path.suffix != ".npz":
        return None
    import json

    from .models.errors import ModelFileError
    from .models.runtime.olf import READ_ERRORS
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
    except READ_ERRORS as e:
        raise ModelFileError(path, f"not a readable exported DACN ({type(e).__name__}: {e})") from None
    pitch = meta.get("pixel_pitch_mm") if isinstance(meta, dict) else None
    return float(pitch) if pitch else None


def check_correction(lens_id: str | None, method: str = "auto", model=None, *, labels=None) -> None:
    """Refuse, before any work, a correction that cannot run whatever the
    image: an unknown method, a network without a lens or a file (``model``),
    a deconvolution without a lens or with a network file. Options are named
    by ``labels`` ({'method', 'model', 'lens'}: the `dcdi correct` options by
    default)."""
    lab = {**CORRECTION_LABELS, **(labels or {})}
    if method not in METHODS:
        raise InputRangeError(lab["method"], method, ", ".join(METHODS))
    dacn = NETWORKS["dacn"]
    shipped = ", ".join(dacn.shipped_keys()) or "none"
    if method == "deconv" and model is not None:
        raise InputRangeError(lab["model"], str(model), f"no network with {lab['method']} deconv (it corrects with "
                              f"the lens's own PSFs); give {lab['method']} dacn or auto to run it")
    if lens_id is None and (method == "deconv" or model is None):
        raise InputRangeError(lab["lens"], None, "the lens that took the capture (its PSFs for the deconvolution"
                              + ("" if method == "deconv" else f", or its shipped DACN; shipped for: {shipped}") + ")"
                              + ("" if method == "deconv" else f", or a DACN file ({lab['model']})"))
    if method == "dacn" and model is None and dacn.shipped_file(lens_id) is None:
        raise ModelError(f"no shipped DACN for lens {lens_id} (shipped for: {shipped}); give {lab['model']} MODEL (a "
                         f"DACN file or run folder), or use the deconvolution ({lab['method']} deconv, any lens)")


def choose_correction(lens_id: str | None, image_pitch_mm: float | None, method: str = "auto", model=None, *,
                      labels=None) -> tuple[str, str]:
    """('deconv' or 'dacn', why in one phrase): how a capture of ``lens_id``
    sampled at ``image_pitch_mm`` (mm per pixel on the sensor) is corrected.

    ``method`` 'deconv': the deconvolution with the lens's PSFs (any lens);
    'dacn': the network ``model`` (a DACN file or run folder) or else the
    lens's shipped one; 'auto': the network ``model`` where one is given,
    else the lens's shipped network where it is recorded better than the
    deconvolution on held-out captures (``models.registry``'s
    ``beats_deconvolution``, decided by ``dcdi report correction``) and the
    image has the pixel pitch it learned (within ``PITCH_TOLERANCE``), else
    the deconvolution. What cannot run is refused as
    :func:`check_correction` says (``labels`` name the options)."""
    check_correction(lens_id, method, model, labels=labels)
    lab = {**CORRECTION_LABELS, **(labels or {})}
    if method != "auto":
        return method, f"asked for: {lab['method']} {method}"
    if model is not None:
        return "dacn", f"a network was given: {lab['model']} {model}"
    dacn = NETWORKS["dacn"]
    path = dacn.shipped_file(lens_id)
    if path is None:
        return "deconv", f"no DACN ships for lens {lens_id}; shipped for {', '.join(dacn.shipped_keys()) or 'none'}"
    if lens_id not in dacn.beats_deconvolution:
        return "deconv", (f"the shipped DACN of {lens_id} is not recorded better than the deconvolution on held-out "
                          f"captures, {REPORT}")
    if image_pitch_mm is None:
        raise InputRangeError("image pixel pitch", None, "the capture's pixel pitch on the sensor (mm): the "
                              f"shipped DACN of {lens_id} serves only the pitch it learned")
    note = pitch_note(trained_pitch_mm(path), image_pitch_mm, f"the shipped DACN of {lens_id}")
    if note:
        return "deconv", note
    return "dacn", (f"the shipped DACN of {lens_id} is recorded better than the deconvolution on held-out captures, "
                    f"{REPORT}, and the image has the pixel pitch it learned")


@dataclass(frozen=True)
class Deconvolution:
    """The camera lens's blur undone with its own PSFs (``correct.deconvolve``).

    lens: the lens that took the capture. options: ``correct.DeconvOptions``
    (None: its defaults). geometry: the capture on that lens's sensor (None:
    it spans the sensor's diagonal). psf_source ('basis', 'olf', 'trace' or
    None: the basis, else the OLF where it covers the request, else traced),
    olf_file, basis_file, kernel_size (an
    explicit kernel, px) and response (the sensor's spectral response) as
    ``runtime.library.psf_source``; settings: the PSF settings (their pitch
    is the geometry's; None: the defaults). reason: why it was chosen.
    labels: the names of the PSF source's choices in its messages
    (``runtime.library.psf_source``'s; None: the CLI's options)."""

    lens: object
    options: object = None
    geometry: object = None
    psf_source: str | None = None
    olf_file: str | None = None
    settings: object = None
    kernel_size: int | None = None
    basis_file: str | None = None
    response: object = None
    reason: str = ""
    labels: object = None

    method = "deconv"

    def run(self, capture, depth_m, progress=None) -> tuple[np.ndarray, dict]:
        """(the sharp image on the capture's grid (H, W, 3) float32, info:
        the deconvolution's, with the PSF source and its message)."""
        from .correct import DeconvOptions, deconvolve
        from .models.runtime.library import psf_source
        from .render.geometry import ImageGeometry
        from .render.simulate import open_library
        h, w = np.shape(capture)[:2]
        geometry = self.geometry or ImageGeometry.full_sensor(self.lens, h, w)
        settings = replace(self.settings, pixel_pitch_mm=None) if self.settings is not None else None
        focus = settings.focus_distance_m if settings is not None else None
        src = psf_source(self.lens, source=self.psf_source, olf_file=self.olf_file, basis_file=self.basis_file,
                         pixel_pitch_mm=geometry.pixel_pitch_mm, settings=settings, kernel_size=self.kernel_size,
                         focus_m=focus, custom_response=self.response is not None, labels=self.labels)
        library = src.library
        if library is None:
            library = open_library(self.lens, geometry, settings, response=self.response, fit_depth_m=depth_m)
        res = deconvolve(capture, depth_m, self.lens, self.options or DeconvOptions(), geometry=geometry,
                         library=library, progress=progress)
        return res.image, {**res.info, "lens": self.lens.id, "pixel_pitch_mm": geometry.pixel_pitch_mm,
                           "psf_source": src.kind, "psf_message": src.message}


@dataclass(frozen=True)
class NetworkCorrection:
    """A DACN (``models.dacn.correct.load_dacn``'s model and info) run tiled
    (``tile``, ``overlap`` px) on a capture clipped to [0, 1], the range it
    learned. A refining network (its spec's ``refine``) reads the capture's
    ``deconvolution`` too, run first; a conditioned one the field of each
    pixel, from ``geometry`` (None: the capture spans the sensor's diagonal).
    reason: why it was chosen. labels: the names of the correction's inputs
    in its messages (:data:`CORRECTION_LABELS`'s keys; None: those)."""

    model: object
    info: dict
    tile: int = 256
    overlap: int = 32
    reason: str = ""
    deconvolution: Deconvolution | None = None
    geometry: object = None
    labels: object = None

    method = "dacn"

    def run(self, capture, depth_m, progress=None) -> tuple[np.ndarray, dict]:
        from .models.dacn.correct import correct
        spec = self.model.spec
        capture = np.clip(capture, 0.0, 1.0)
        geometry, dec, dec_info = self.geometry, None, None
        if spec.refine or spec.condition:
            if self.deconvolution is None:
                lab = {**CORRECTION_LABELS, **(self.labels or {})}
                raise ModelError(f"{self.info.get('checkpoint')}: this network "
                                 + ("refines the deconvolution with" if spec.refine else "reads the field of")
                                 + f" the capture's lens; name the lens ({lab['lens']})")
            if geometry is None:
                from .render.geometry import ImageGeometry
                geometry = ImageGeometry.full_sensor(self.deconvolution.lens, *np.shape(capture)[:2])
        from .models.dacn.unaware import told_depth, told_depth_map
        told = told_depth(self.info)
        deconvolution = self.deconvolution
        if told is not None:      # trained told one depth: told it here too, refining the one-depth deconvolution
            depth_m = told_depth_map(np.asarray(depth_m, np.float32), told)
            if spec.refine:
                from .correct import DeconvOptions
                deconvolution = replace(deconvolution, options=replace(deconvolution.options or DeconvOptions(),
                                                                       one_depth_m=told))
        if spec.refine:
            dec, dec_info = replace(deconvolution, geometry=geometry).run(capture, depth_m)
        out = correct(self.model, capture, depth_m, deconvolved=dec, geometry=geometry, tile=self.tile,
                      overlap=self.overlap, progress=progress)
        info = {"model": self.info.get("checkpoint"), "trained_for": trained_lens(self.info),
                "pixel_pitch_mm": (self.info.get("meta") or {}).get("pixel_pitch_mm"),
                "device": self.info.get("device")}
        if dec_info is not None:
            info["deconvolution"] = dec_info
        return np.clip(out, 0.0, None).astype(np.float32), info


def trained_lens(info: dict) -> str | None:
    """The lens a loaded DACN (its ``load_dacn`` info) was trained for, if recorded."""
    return (info.get("meta") or {}).get("lens") or (info.get("da2t") or {}).get("lens")


def load_network(path, lens_id: str | None, *, weights: str = "ema", device: str = "cpu", tile: int = 256,
                 overlap: int = 32, reason: str = "", labels=None) -> NetworkCorrection:
    """The DACN of ``path`` as a correction, refused when it was trained for
    another lens than ``lens_id`` (None: not checked); ``labels`` as
    :class:`NetworkCorrection`'s."""
    from .models.dacn.correct import load_dacn
    model, info = load_dacn(path, weights=weights, device=device)
    trained = trained_lens(info)
    if lens_id is not None and trained is not None and trained != lens_id:
        raise ModelError(f"{path} was trained for lens {trained}, not {lens_id}")
    return NetworkCorrection(model, info, tile, overlap, reason, labels=labels)


def correction_for(camera, geometry, method: str = "auto", model=None, *, deconvolution: Deconvolution | None = None,
                   weights: str = "ema", device: str = "cpu", tile: int = 256, overlap: int = 32, labels=None):
    """The correction :func:`choose_correction` picks for a capture of the
    lens ``camera`` (None: only a given network) lying at ``geometry`` on its
    sensor (``render.geometry.ImageGeometry``): a :class:`Deconvolution`
    (``deconvolution``'s settings, else the defaults, for ``camera`` at
    ``geometry``) or a :class:`NetworkCorrection` (``model``, or the lens's
    shipped DACN, loaded with ``weights`` on ``device``); ``labels`` name
    the options in every message (the deconvolution's own ``labels``, where
    set, for its PSF source)."""
    lens_id = camera.id if camera is not None else None
    pitch = geometry.pixel_pitch_mm if geometry is not None else None
    chosen, reason = choose_correction(lens_id, pitch, method, model, labels=labels)
    template = deconvolution or Deconvolution(camera)
    if template.labels is None and labels is not None:
        template = replace(template, labels=labels)
    if chosen == "deconv":
        return replace(template, lens=camera, geometry=geometry, reason=reason)
    path = model if model is not None else NETWORKS["dacn"].shipped_file(lens_id)
    net = load_network(path, lens_id, weights=weights, device=device, tile=tile, overlap=overlap, reason=reason,
                       labels=labels)
    if camera is None:
        return net
    return replace(net, deconvolution=replace(template, lens=camera, geometry=geometry), geometry=geometry)


# ------------------------------------------------------------------ the stages
def recover(capture, *, camera_pitch_mm: float | None = None, depth_m=None, estimator=None, correction=None,
            corrector=None, corrector_info: dict | None = None, tile: int = 256, seconds: dict | None = None,
            notes=None, record: dict | None = None, progress=None):
    """Stages 1-2: (corrected image, depth m, depth source).

    ``correction``: a :class:`Deconvolution` or :class:`NetworkCorrection`
    (:func:`correction_for`), or None: no correction (a sharp input).
    ``corrector`` / ``corrector_info``: a loaded DACN and its info, the same
    as ``correction=NetworkCorrection(corrector, corrector_info, tile)``.
    ``camera_pitch_mm``: the capture's pixel pitch, for the note when a
    network learned another. Filled when given: ``seconds`` per stage,
    ``notes`` (lines for the user), ``record`` (the correction's method,
    why, and its own info). The deconvolution runs with the depth used here,
    the estimated one when none is given."""
    seconds = {} if seconds is None else seconds
    notes = [] if notes is None else notes
    record = {} if record is None else record
    if correction is None and corrector is not None:
        correction = NetworkCorrection(corrector, corrector_info or {}, tile)
    img = np.asarray(capture, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("capture shape", img.shape, "(H, W, 3)")
    depth, source = _depth(img, depth_m, estimator, seconds)
    if correction is None:
        record.update({"method": "none", "reason": "a sharp input: no correction"})
        return img, depth, source
    if correction.method == "dacn":
        trained = (correction.info.get("meta") or {}).get("pixel_pitch_mm")
        note = pitch_note(trained, camera_pitch_mm, "the correction network") if camera_pitch_mm else None
        if note:
            notes.append(note)
    t0 = time.perf_counter()
    corrected, info = correction.run(img, depth, progress)
    seconds["correction"] = time.perf_counter() - t0
    record.update({"method": correction.method, "reason": correction.reason,
                   **{k: v for k, v in info.items() if k != "method"}})
    return corrected, depth, source


def _depth(img, depth_m, estimator, seconds):
    """(depth m, its source): the given map, else the estimator's."""
    if depth_m is not None:
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != img.shape[:2]:
            raise InputRangeError("depth map shape", depth.shape, f"{img.shape[:2]}, the capture's")
        return depth, "given"
    # the estimators are imported only when one is needed (the add-on bundles no depth network)
    from .models.depth.estimators import DepthEstimator
    if not isinstance(estimator, DepthEstimator):
        raise ModelError("no depth map and no depth estimator: give a depth map, or an estimator "
                         "(the shipped depth network of the camera lens, or a public one from a checkpoint)")
    t0 = time.perf_counter()
    depth = estimator.estimate(img)
    seconds["depth"] = time.perf_counter() - t0
    return depth, estimator.name


def dof(capture, target_lens, *, keep=None, focus_m=None, depth_m=None, estimator=None, correction=None,
        camera=None, corrector=None, corrector_info=None, camera_pitch_mm=None, psf_source=None, olf_file=None,
        settings=None, geometry=None, tile: int = 256, basis_file=None, **bokeh_kw) -> DofResult:
    """The whole pipeline (module docstring). ``target_lens``: a Lens;
    ``keep`` (near, far) m and/or ``focus_m`` (m or 'prescribed') as
    ``render.simulate.BokehOptions``. The correction: ``correction`` a prepared one
    (:func:`correction_for`), or a method ('auto', 'deconv', 'dacn') for the
    lens ``camera`` (the rule of :func:`choose_correction`; the capture at
    ``camera_pitch_mm``, default: it spans the camera's sensor diagonal), or
    ``corrector`` a loaded DACN (with ``corrector_info``), or none of them
    for a sharp input. ``psf_source`` None / 'basis' / 'olf' / 'trace',
    ``olf_file`` and ``basis_file`` as ``runtime.library.psf_source`` (the target's PSFs, and the camera's
    for a deconvolution chosen here); the rest are fields of
    ``render.simulate.BokehOptions``."""
    from .models.runtime.library import psf_source as choose_source
    from .render.geometry import ImageGeometry
    from .render.simulate import BokehOptions, bokeh
    options = BokehOptions(keep=keep, focus_m=focus_m, settings=settings, geometry=geometry, **bokeh_kw)
    h, w = np.shape(capture)[:2]
    if isinstance(correction, str):
        if camera is None:
            raise InputRangeError("camera", None, f"the lens that took the capture (correction {correction!r})")
        cam_geom = (ImageGeometry.full_sensor(camera, h, w) if camera_pitch_mm is None else
                    ImageGeometry.from_pixel_pitch(camera, h, w, camera_pitch_mm))
        template = Deconvolution(camera, psf_source=psf_source, olf_file=olf_file, settings=settings,
                                 response=bokeh_kw.get("response"), basis_file=basis_file)
        correction = correction_for(camera, cam_geom, correction, deconvolution=template, tile=tile)
        camera_pitch_mm = cam_geom.pixel_pitch_mm
    seconds, notes, record = {}, [], {}
    corrected, depth, dsrc = recover(capture, camera_pitch_mm=camera_pitch_mm, depth_m=depth_m, estimator=estimator,
                                     correction=correction, corrector=corrector, corrector_info=corrector_info,
                                     tile=tile, seconds=seconds, notes=notes, record=record)
    geometry = geometry or ImageGeometry.full_sensor(target_lens, h, w)
    t0 = time.perf_counter()
    src = choose_source(target_lens, source=psf_source, olf_file=olf_file, basis_file=basis_file,
                        pixel_pitch_mm=geometry.pixel_pitch_mm,
                        settings=settings, focus_m=None if focus_m in (None, "prescribed") else focus_m)
    r = bokeh(corrected, depth, target_lens, replace(options, geometry=geometry), library=src.library)
    seconds["psfs and bokeh"] = time.perf_counter() - t0
    return DofResult(r.image, corrected, depth, dsrc, src.kind, src.message, seconds, notes, dict(r.info), record)
