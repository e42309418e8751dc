"""The application layer: every job a user asks for, as a typed request and
result, for both front ends (the `dcdi` command and the Blender add-on).

A front end translates its inputs (options, panel settings, pixels) into a
request, calls the job with a :class:`Control` (progress by stage, cancel),
and translates the result back (files, Blender images, lines for the user).
The decisions (which PSFs, which correction, the capture's recorded
geometry as defaults, what the user is told) are made here once. Errors name
the request's fields (``errors.field``); each front end shows them in its
own words (``DcdiError.in_words``).

    simulate(SimulateRequest) -> SimulateResult     a lens's aberrations
    bokeh(BokehRequest) -> BokehResult              a lens's depth of field
    correct(CorrectRequest) -> CorrectResult        a lens's blur undone
    dof(DofRequest) -> DofResult                    capture -> another lens's depth of field
    open_source(lens, geometry, PSFRequest)         the PSFs of a job, always a library
    DEFAULT_BUDGET_DB                               each job's default error budget (dB; psf.budget)

Units: depths in metres, lengths on the sensor in mm, positions in pixels.
"""
from ..caches import clear as clear_caches, sizes as cache_sizes
from ..control import Cancelled, Control
from ..psf.budget import DEFAULT_DB as DEFAULT_BUDGET_DB
from ..psf.sources import PREVIEW_TRACE, PSFRequest, PSFSourceResult, open_source
from .correction import CorrectRequest, CorrectResult, correct, prepare
from .frame import CaptureFrame, capture_frame
from .pipeline import DofRequest, DofResult, dof
from .render import BokehRequest, BokehResult, SimulateRequest, SimulateResult, bokeh, simulate
from .sources import SourceCache

__all__ = ["Cancelled", "Control", "PSFRequest", "PSFSourceResult", "SourceCache", "open_source", "PREVIEW_TRACE",
           "DEFAULT_BUDGET_DB",
           "SimulateRequest", "SimulateResult", "simulate", "BokehRequest", "BokehResult", "bokeh",
           "CorrectRequest", "CorrectResult", "correct", "prepare", "CaptureFrame", "capture_frame",
           "DofRequest", "DofResult", "dof", "clear_caches", "cache_sizes"]
