"""DCDI end to end: one minimalist-lens capture -> the depth of field of any lens.

The paper's I_A: recover the all-in-focus image I_R (DACN) and the depth
D_P (a monocular estimator), then render a target lens's depth of field on
them, keeping a depth range sharp (or focusing), with that lens's PSFs from
the Omni-Lens-Field where it covers the request, else traced.

The stages, in the order the data need them (DACN takes the depth map, so
depth comes first; the paper estimates it on the aberrated capture too):

1. depth: the given map, else the estimator's (``models.depth``);
2. correction: DACN on the capture with that depth (``camera`` None: the
   image is already sharp and is passed on untouched);
3. PSFs and bokeh: ``render.simulate.bokeh`` of the target lens (the PSF
   source from ``runtime.library.psf_source``; only the depth bins the map
   touches are filled).

Nothing a scene does not need is computed: no estimator is loaded when a
depth map is given, no network when the camera is 'none'.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

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
    psf_source: str                     # 'olf' or 'trace'
    psf_message: str
    seconds: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


def pitch_note(trained_mm: float | None, image_mm: float, what: str) -> str | None:
    """A note when an image's pixel pitch is not the one a network learned."""
    if not trained_mm or abs(image_mm / trained_mm - 1) <= PITCH_TOLERANCE:
        return None
    return (f"{what} learned {trained_mm * 1000:.4g} um pixels, this image has {image_mm * 1000:.4g} um "
            f"({image_mm / trained_mm:.2f}x): its blur is {trained_mm / image_mm:.2f}x the size it was trained on")


def recover(capture, *, camera_pitch_mm: float | None = None, depth_m=None, estimator=None, corrector=None,
            corrector_info: dict | None = None, tile: int = 256, seconds: dict | None = None, notes=None):
    """Stages 1-2: (corrected image, depth m, depth source). ``corrector``
    None: no correction (a sharp input)."""
    seconds = {} if seconds is None else seconds
    notes = [] if notes is None else notes
    img = np.asarray(capture, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("capture shape", img.shape, "(H, W, 3)")
    if depth_m is not None:
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != img.shape[:2]:
            raise InputRangeError("depth map shape", depth.shape, f"{img.shape[:2]}, the capture's")
        source = "given"
    else:
        # the estimators are imported only when one is needed (the add-on bundles no depth network)
        from .models.depth.estimators import DepthEstimator
        if not isinstance(estimator, DepthEstimator):
            raise ModelError("no depth map and no depth estimator: give a depth map, or an estimator "
                             "(the shipped depth network of the camera lens, or a public one from a checkpoint)")
        t0 = time.perf_counter()
        depth = estimator.estimate(img)
        seconds["depth"] = time.perf_counter() - t0
        source = estimator.name
    if corrector is None:
        return img, depth, source
    from .models.dacn.correct import correct
    trained = (corrector_info or {}).get("meta", {}).get("pixel_pitch_mm")
    note = pitch_note(trained, camera_pitch_mm, "the correction network") if camera_pitch_mm else None
    if note:
        notes.append(note)
    t0 = time.perf_counter()
    corrected = correct(corrector, np.clip(img, 0.0, 1.0), depth, tile=tile)
    seconds["correction"] = time.perf_counter() - t0
    return np.clip(corrected, 0.0, None).astype(np.float32), depth, source


def dof(capture, target_lens, *, keep=None, focus_m=None, depth_m=None, estimator=None, corrector=None,
        corrector_info=None, camera_pitch_mm=None, psf_source=None, olf_file=None, settings=None, geometry=None,
        tile: int = 256, **bokeh_kw) -> DofResult:
    """The whole pipeline (module docstring). ``target_lens``: a Lens;
    ``keep`` (near, far) m or ``focus_m`` (m or 'prescribed') as
    ``render.simulate.bokeh``; ``corrector``: a DACN (``models.correct.
    load_dacn``) or None for a sharp input; ``psf_source`` None / 'olf' /
    'trace' and ``olf_file`` as ``runtime.library.psf_source``; the rest are
    fields of ``render.simulate.BokehOptions``."""
    from dataclasses import replace

    from .render.geometry import ImageGeometry
    from .render.simulate import BokehOptions, bokeh
    from .models.runtime.library import psf_source as choose_source
    if (keep is None) == (focus_m is None):
        raise InputRangeError("keep / focus", (keep, focus_m), "exactly one of them")
    options = BokehOptions(keep=keep, focus_m=focus_m, settings=settings, geometry=geometry, **bokeh_kw)
    seconds, notes = {}, []
    corrected, depth, dsrc = recover(capture, camera_pitch_mm=camera_pitch_mm, depth_m=depth_m, estimator=estimator,
                                     corrector=corrector, corrector_info=corrector_info, tile=tile, seconds=seconds,
                                     notes=notes)
    h, w = corrected.shape[:2]
    geometry = geometry or ImageGeometry.full_sensor(target_lens, h, w)
    t0 = time.perf_counter()
    src = choose_source(target_lens, source=psf_source, olf_file=olf_file, pixel_pitch_mm=geometry.pixel_pitch_mm,
                        settings=settings, focus_m=None if focus_m in (None, "prescribed") else focus_m)
    r = bokeh(corrected, depth, target_lens, replace(options, geometry=geometry), library=src.library)
    seconds["psfs and bokeh"] = time.perf_counter() - t0
    return DofResult(r.image, corrected, depth, dsrc, src.kind, src.message, seconds, notes, dict(r.info))
