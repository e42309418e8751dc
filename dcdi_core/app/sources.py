"""The PSF source of a job: which PSFs serve it (the lens's basis, the
Omni-Lens-Field, or tracing), always as a library the renderer can use.

``models.runtime.library.psf_source`` decides between the basis and the OLF
and says why; here a traced library is opened too (``render.simulate.
open_library``), so no caller writes its own fallback, and a
:class:`SourceCache` keeps the last few sources between jobs (an OLF or basis
library keeps the bins it computed: the frames of an animation pay them once).

Units: pixel pitch in mm on the sensor, focus and depths in metres.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from ..psf.compute import PSFSettings
from .control import Control

# Traced PSFs for a preview (the add-on's viewport) where no shipped basis or
# OLF holds the request: fewer pupil rays and wavelengths, a proxy of the
# render's (docs/addon.md gives its error and time against the full trace).
PREVIEW_TRACE = {"pupil_samples": 24, "n_wavelengths": 9}


@dataclass(frozen=True)
class PSFRequest:
    """Which PSFs a job asks for.

    ``source``: 'basis', 'olf', 'trace' or None (the basis where it covers
    the request, else the OLF, else traced). ``olf_file`` / ``basis_file``:
    files instead of the shipped ones. ``settings``: the PSF settings (their
    ``focus_distance_m`` the focus, metres, None: as prescribed; their pitch
    is the image's). ``kernel_size``: an explicit kernel (px; None: the
    settings', grown to hold the blur where ``fit_kernel``). ``response``:
    the sensor's spectral response (None: the shipped curves). ``preview``:
    PSFs that must be traced are traced with :data:`PREVIEW_TRACE`."""

    source: str | None = None
    olf_file: str | None = None
    basis_file: str | None = None
    settings: PSFSettings | None = None
    kernel_size: int | None = None
    response: object = None
    fit_kernel: bool = True
    preview: bool = False

    def __post_init__(self):
        from ..errors import InputRangeError
        from ..models.runtime.library import SOURCES
        if self.source not in (None,) + SOURCES:
            raise InputRangeError("psf_source", self.source,
                                  "basis, olf, trace, or none (the first of basis and olf that covers the request)")
        if self.settings is not None and not isinstance(self.settings, PSFSettings):
            raise InputRangeError("settings", self.settings, "PSFSettings, or None for the defaults")

    @property
    def focus_m(self) -> float | None:
        return None if self.settings is None else self.settings.focus_distance_m

    def focused(self, focus_m: float | None) -> "PSFRequest":
        """The same request with the PSFs focused at ``focus_m`` (m, None: as prescribed)."""
        return replace(self, settings=replace(self.settings or PSFSettings(), focus_distance_m=focus_m))


@dataclass
class PSFSourceResult:
    """The PSFs serving a job: ``kind`` ('basis', 'olf' or 'trace'), why
    (``message``, one line), ``library`` (always set), the files and the
    ``quality`` ('full', or 'preview' for a preview's lighter trace)."""

    kind: str
    message: str
    library: object
    olf_file: str | None = None
    basis_file: str | None = None
    quality: str = "full"

    def as_dict(self) -> dict:
        return {"psf_source": self.kind, "psf_message": self.message, "psf_quality": self.quality,
                "olf_file": self.olf_file if self.kind == "olf" else None,
                "basis_file": self.basis_file if self.kind == "basis" else None}


def _choose(lens, geometry, request: PSFRequest):
    from ..models.runtime.library import psf_source
    return psf_source(lens, source=request.source, olf_file=request.olf_file, basis_file=request.basis_file,
                      pixel_pitch_mm=geometry.pixel_pitch_mm, settings=request.settings,
                      kernel_size=request.kernel_size, focus_m=request.focus_m,
                      custom_response=request.response is not None)


def open_source(lens, geometry, request: PSFRequest, *, fit_depth_m=None, control: Control | None = None,
                chosen=None) -> PSFSourceResult:
    """The PSFs of ``lens`` for an image at ``geometry`` (``render.geometry.
    ImageGeometry``) as ``request`` asks: the basis or OLF library where one
    serves it, else a traced library (cached on disk) whose kernel grows to
    hold the blur of ``fit_depth_m`` (a depth map, metres; with
    ``request.fit_kernel``). ``control`` reports the PSFs traced (stage
    'PSFs') and stops the trace when cancelled. ``chosen``: the source
    already chosen for this request (``psf_source``'s), not chosen again."""
    from ..render.simulate import open_library
    control = control or Control()
    src = chosen if chosen is not None else _choose(lens, geometry, request)
    control.say(src.message)
    if src.library is not None:
        return PSFSourceResult(src.kind, src.message, src.library, src.olf_file, src.basis_file)
    settings, quality = request.settings or PSFSettings(), "full"
    if request.preview:
        settings, quality = replace(settings, **PREVIEW_TRACE), "preview"
    library = open_library(lens, geometry, settings, response=request.response,
                           fit_depth_m=fit_depth_m if request.fit_kernel else None, progress=control.counter("PSFs"))
    return PSFSourceResult("trace", src.message, library, src.olf_file, src.basis_file, quality)


def ensure_bins(library, depth_m, control: Control | None = None) -> None:
    """Compute now every depth bin from the nearest to the farthest valid
    depth of ``depth_m`` (metres), so that progress and cancel work while
    PSFs are built (a patch's mean inverse depth can fall in a bin no pixel
    touches, hence the whole span)."""
    d = np.asarray(depth_m, np.float64)
    d = d[d > 0]                    # NaN, 0 and negative depths are left sharp
    if d.size == 0:
        return
    need = library.bins_needed(d, clamp_near=True)
    control = control or Control()
    library.ensure(bins=np.arange(need.min(), need.max() + 1), progress=control.counter("PSFs"))


class SourceCache:
    """The PSF sources of the last ``size`` requests (lens file and its
    modification time, pixel pitch, PSF request), for a front end that runs
    many jobs on one lens (the add-on's preview, an animation)."""

    def __init__(self, size: int = 6):
        self.size = size
        self._kept: OrderedDict = OrderedDict()

    def _key(self, lens, geometry, request: PSFRequest):
        path = str(getattr(lens, "path", "") or "")
        mtime = os.stat(path).st_mtime_ns if path and os.path.exists(path) else None
        response = None if request.response is None else id(request.response)
        return (lens.id, path, mtime, round(float(geometry.pixel_pitch_mm), 12),
                replace(request, response=None), response)

    def chosen(self, lens, geometry, request: PSFRequest):
        """``psf_source``'s choice for this request, kept."""
        key = self._key(lens, geometry, request)
        if key in self._kept:
            self._kept.move_to_end(key)
            return self._kept[key]
        src = _choose(lens, geometry, request)
        self._kept[key] = src
        while len(self._kept) > self.size:
            self._kept.popitem(last=False)
        return src

    def clear(self) -> None:
        self._kept.clear()
