"""The correction of a lens's blur: which correction runs, and how.

The rule (:func:`choose_correction`): the deconvolution with the lens's own
PSFs (:class:`Deconvolution`, ``dcdi_core.correct``: any lens, no training),
or the lens's shipped network (:class:`NetworkCorrection`, a DACN) where
that network is recorded better than the deconvolution and the image has the
pixel pitch it learned. The jobs that use them (``app.correct``, the DCDI
chain ``app.dof``: depth -> correction -> the target lens's bokeh) live in
the application layer, ``dcdi_core.app``.

Nothing a scene does not need is computed: no network is loaded when the
deconvolution corrects.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputRangeError, field
from ..errors import ModelError
from ..psf.pitch import NETWORK_PITCH_RTOL, learned_pitch_holds
from ..shipped import NETWORKS

def shipped_model(kind: str, lens_id: str) -> Path | None:
    """The shipped ``kind`` ('dacn' or 'depth') file for a lens, or None."""
    if kind not in ("dacn", "depth"):
        raise InputRangeError("shipped model kind", kind, "dacn or depth")
    return NETWORKS[kind].shipped_file(lens_id)


def shipped_lenses(kind: str) -> list[str]:
    return NETWORKS[kind].shipped_keys()


def pitch_note(trained_mm: float | None, image_mm: float, what: str) -> str | None:
    """A note when an image's pixel pitch is not the one a network learned."""
    if not trained_mm or learned_pitch_holds(image_mm, trained_mm, NETWORK_PITCH_RTOL):
        return None
    return (f"{what} learned {trained_mm * 1000:.4g} um pixels, this image has {image_mm * 1000:.4g} um "
            f"({image_mm / trained_mm:.2f}x): its blur is {trained_mm / image_mm:.2f}x the size it was trained on")


# ------------------------------------------------------------------ which correction
METHODS = ("auto", "deconv", "dacn")

REPORT = "the DACN study (docs/correction.md)"


def trained_pitch_mm(path) -> float | None:
    """The pixel pitch (mm) a DACN file (.npz) learned, from its metadata
    record alone (None: not recorded, or a run folder / checkpoint)."""
    path = Path(path)
    if path.suffix != ".npz":
        return None
    from ..io.model_npz import read_npz_with_meta
    meta, _ = read_npz_with_meta(path, "an exported DACN")          # bounded, checked (io.npzfile)
    pitch = meta.get("pixel_pitch_mm") if isinstance(meta, dict) else None
    return float(pitch) if pitch else None


def check_correction(lens_id: str | None, method: str = "auto", model=None) -> None:
    """Refuse, before any work, a correction that cannot run whatever the
    image: an unknown method, a network without a lens or a file (``model``),
    a deconvolution without a lens or with a network file. The request's
    fields are named ``method``, ``model`` and ``lens`` (each front end
    shows them in its words)."""
    method_, model_ = field("method"), field("model")
    if method not in METHODS:
        raise InputRangeError("method", method, ", ".join(METHODS))
    dacn = NETWORKS["dacn"]
    shipped = ", ".join(dacn.shipped_keys()) or "none"
    if method == "deconv" and model is not None:
        raise InputRangeError("model", str(model), f"no network with {method_} deconv (it corrects with "
                              f"the lens's own PSFs); give {method_} dacn or auto to run it")
    if lens_id is None and (method == "deconv" or model is None):
        raise InputRangeError("lens", None, "the lens that took the capture (its PSFs for the deconvolution"
                              + ("" if method == "deconv" else f", or its shipped DACN; shipped for: {shipped}") + ")"
                              + ("" if method == "deconv" else f", or a DACN file ({model_})"))
    if method == "dacn" and model is None and dacn.shipped_file(lens_id) is None:
        raise ModelError(f"no shipped DACN for lens {lens_id} (shipped for: {shipped}); give {model_} (a "
                         f"DACN file or run folder), or use the deconvolution ({method_} deconv, any lens)")


def choose_correction(lens_id: str | None, image_pitch_mm: float | None, method: str = "auto",
                      model=None, *, checked: bool = False) -> tuple[str, str]:
    """('deconv' or 'dacn', why in one phrase): how a capture of ``lens_id``
    sampled at ``image_pitch_mm`` (mm per pixel on the sensor) is corrected.

    ``method`` 'deconv': the deconvolution with the lens's PSFs (any lens);
    'dacn': the network ``model`` (a DACN file or run folder) or else the
    lens's shipped one; 'auto': the network ``model`` where one is given,
    else the lens's shipped network where it is recorded better than the
    deconvolution on held-out captures (``shipped``'s
    ``beats_deconvolution``, decided by ``python -m lab report correction``) and the
    image has the pixel pitch it learned (within ``psf.pitch.NETWORK_PITCH_RTOL``), else
    the deconvolution. What cannot run is refused as
    :func:`check_correction` says (``checked``: the caller's request was, when made)."""
    if not checked:
        check_correction(lens_id, method, model)
    if method != "auto":
        return method, f"asked for: {field('method')} {method}"
    if model is not None:
        return "dacn", f"a network was given: {field('model')} {model}"
    dacn = NETWORKS["dacn"]
    path = dacn.shipped_file(lens_id)
    if path is None:
        return "deconv", f"no DACN ships for lens {lens_id}; shipped for {', '.join(dacn.shipped_keys()) or 'none'}"
    if lens_id not in dacn.beats_deconvolution:
        return "deconv", (f"the shipped DACN of {lens_id} is not recorded better than the deconvolution on held-out "
                          f"captures, {REPORT}")
    if image_pitch_mm is None:
        raise InputRangeError("image_pixel_pitch_mm", None, "the capture's pixel pitch on the sensor (mm): the "
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
    it spans the sensor's diagonal). psf: its PSFs (``psf.sources.
    PSFRequest``: the source, files, settings, kernel and spectral
    response; the settings' pitch is the geometry's). reason: why it was
    chosen. sources: the job's ``app.sources.SourceCache`` (None: the PSFs
    opened for this run alone), which the depth estimate of the same
    capture shares."""

    lens: object
    options: object = None
    geometry: object = None
    psf: object = None
    reason: str = ""
    sources: object = dataclasses.field(default=None, compare=False, repr=False)

    method = "deconv"

    def run(self, capture, depth_m, progress=None, psf_progress=None) -> tuple[np.ndarray, dict]:
        """(the sharp image on the capture's grid (H, W, 3) float32, info:
        the deconvolution's, with the PSF source and its message).
        ``progress(done, total)``: windows; ``psf_progress``: PSFs traced."""
        from ..control import Control
        from ..psf.sources import PSFRequest, open_source
        from ..correct import DeconvOptions, deconvolve
        from ..render.geometry import ImageGeometry
        h, w = np.shape(capture)[:2]
        geometry = self.geometry or ImageGeometry.full_sensor(self.lens, h, w)
        request = self.psf or PSFRequest()
        if request.settings is not None:
            request = replace(request, settings=replace(request.settings, pixel_pitch_mm=None))
        control = Control(progress=None if psf_progress is None else (lambda stage, d, t: psf_progress(d, t)))
        opened = self.sources.open if self.sources is not None else open_source
        src = opened(self.lens, geometry, request, fit_depth_m=depth_m, control=control)
        res = deconvolve(capture, depth_m, self.lens, self.options or DeconvOptions(), geometry=geometry,
                         library=src.library, progress=progress)
        return res.image, {**res.info, "lens": self.lens.id, "pixel_pitch_mm": geometry.pixel_pitch_mm,
                           "psf_source": src.kind, "psf_message": src.message}


@dataclass(frozen=True)
class NetworkCorrection:
    """A DACN (``models.dacn.correct.load_dacn``'s model and info) run tiled
    (``tile``, ``overlap`` px) on a capture clipped to [0, 1], the range it
    learned. A refining network (its spec's ``refine``) reads the capture's
    ``deconvolution`` too, run first; a conditioned one the field of each
    pixel, from ``geometry`` (None: the capture spans the sensor's diagonal).
    reason: why it was chosen."""

    model: object
    info: dict
    tile: int = 256
    overlap: int = 32
    reason: str = ""
    deconvolution: Deconvolution | None = None
    geometry: object = None

    method = "dacn"

    def run(self, capture, depth_m, progress=None, psf_progress=None) -> tuple[np.ndarray, dict]:
        from ..models.dacn.correct import correct
        spec = self.model.spec
        capture = np.clip(capture, 0.0, 1.0)
        geometry, dec, dec_info = self.geometry, None, None
        if spec.refine or spec.condition:
            if self.deconvolution is None:
                raise ModelError(f"{self.info.get('checkpoint')}: this network "
                                 + ("refines the deconvolution with" if spec.refine else "reads the field of")
                                 + f" the capture's lens; name the lens ({field('lens')})")
            if geometry is None:
                from ..render.geometry import ImageGeometry
                geometry = ImageGeometry.full_sensor(self.deconvolution.lens, *np.shape(capture)[:2])
        from ..models.dacn.unaware import told_depth, told_depth_map
        told = told_depth(self.info)
        deconvolution = self.deconvolution
        if told is not None:      # trained told one depth: told it here too, refining the one-depth deconvolution
            depth_m = told_depth_map(np.asarray(depth_m, np.float32), told)
            if spec.refine:
                from ..correct import DeconvOptions
                deconvolution = replace(deconvolution, options=replace(deconvolution.options or DeconvOptions(),
                                                                       one_depth_m=told))
        if spec.refine:
            dec, dec_info = replace(deconvolution, geometry=geometry).run(capture, depth_m, psf_progress=psf_progress)
        out = correct(self.model, capture, depth_m, deconvolved=dec, geometry=geometry, tile=self.tile,
                      overlap=self.overlap, progress=progress)
        info = {"model": self.info.get("checkpoint"), "trained_for": trained_lens(self.info),
                "pixel_pitch_mm": (self.info.get("meta") or {}).get("pixel_pitch_mm"),
                "device": self.info.get("device")}
        if dec_info is not None:
            info["deconvolution"] = dec_info
            info["psf_source"] = dec_info["psf_source"]
            info["psf_message"] = f"the deconvolution it refined: {dec_info['psf_message']}"
        return np.clip(out, 0.0, None).astype(np.float32), info


def trained_lens(info: dict) -> str | None:
    """The lens a loaded DACN (its ``load_dacn`` info) was trained for, if recorded."""
    return (info.get("meta") or {}).get("lens") or (info.get("da2t") or {}).get("lens")


def check_trained_for(info: dict, lens_id: str | None, path) -> None:
    """Refuse a DACN (its ``load_dacn`` info) trained for another lens than ``lens_id`` (None: not checked)."""
    trained = trained_lens(info)
    if lens_id is not None and trained is not None and trained != lens_id:
        raise ModelError(f"{path} was trained for lens {trained}, not {lens_id}")


def load_network(path, lens_id: str | None, *, weights: str = "ema", device: str = "cpu", tile: int = 256,
                 overlap: int = 32, reason: str = "") -> NetworkCorrection:
    """The DACN of ``path`` as a correction, refused when it was trained for
    another lens than ``lens_id`` (None: not checked). ``app.correct`` is
    the whole job (the rule, the refining deconvolution, the geometry)."""
    from ..models.dacn.correct import load_dacn
    model, info = load_dacn(path, weights=weights, device=device)
    check_trained_for(info, lens_id, path)
    return NetworkCorrection(model, info, tile, overlap, reason)


# ------------------------------------------------------------------ the correction stage
def recover(capture, depth_m, correction, progress=None, *, psf_progress=None) -> tuple[np.ndarray, dict]:
    """Stage 2: (the sharp estimate (H, W, 3) float32, the correction's info)
    of ``capture`` (H, W, 3) linear with its depth ``depth_m`` (H, W) metres
    by ``correction`` (a :class:`Deconvolution` or :class:`NetworkCorrection`;
    ``app.correction.prepare`` picks it). ``progress(done, total)``: its
    windows or tiles; ``psf_progress``: PSFs traced."""
    img = np.asarray(capture, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("capture", img.shape, "(H, W, 3)")
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.shape != img.shape[:2]:
        raise InputRangeError("depth_m", depth.shape, f"{img.shape[:2]}, the capture's")
    return correction.run(img, depth, progress, psf_progress)
