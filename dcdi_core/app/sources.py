"""The PSF sources a front end keeps between jobs: :class:`SourceCache`
holds the last few sources (an OLF or basis library keeps the bins it
computed: the frames of an animation pay them once). Which PSFs serve a job,
and opening them, is ``psf.sources`` (the rule, the basis, the OLF and the
traced library in one place).

Units: pixel pitch in mm on the sensor.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import replace

from ..optics.lens import lens_fingerprint
from ..psf.sources import PSFRequest, PSFSourceResult, choose, open_source


class SourceCache:
    """The PSF sources of the last ``size`` requests (the lens: its file, the
    file's modification time and its optical fingerprint, which tells a
    stop or its blades' turn apart; pixel pitch, PSF request), for a front
    end that runs many jobs on one lens (the add-on's preview, an animation)."""

    def __init__(self, size: int = 6):
        self.size = size
        self._kept: OrderedDict = OrderedDict()

    def _key(self, lens, geometry, request: PSFRequest):
        path = str(getattr(lens, "path", "") or "")
        mtime = os.stat(path).st_mtime_ns if path and os.path.exists(path) else None
        response = None if request.response is None else id(request.response)
        # the pitch is the geometry's: settings that carry it ask for the same PSFs as those that leave it out
        settings = None if request.settings is None else replace(request.settings, pixel_pitch_mm=None)
        return (lens.id, path, mtime, lens_fingerprint(lens), round(float(geometry.pixel_pitch_mm), 12),
                replace(request, response=None, settings=settings), response)

    def chosen(self, lens, geometry, request: PSFRequest):
        """``psf_source``'s choice for this request, kept."""
        key = self._key(lens, geometry, request)
        if key in self._kept:
            self._kept.move_to_end(key)
            return self._kept[key]
        src = choose(lens, geometry, request)
        self._kept[key] = src
        while len(self._kept) > self.size:
            self._kept.popitem(last=False)
        return src

    def open(self, lens, geometry, request: PSFRequest, *, fit_depth_m=None, control=None) -> PSFSourceResult:
        """``psf.sources.open_source`` from the kept choice: a source opened
        again at the same settings serves the bins it made (``PSFSource.opened``)."""
        return open_source(lens, geometry, request, fit_depth_m=fit_depth_m, control=control,
                           chosen=self.chosen(lens, geometry, request))

    def clear(self) -> None:
        self._kept.clear()
