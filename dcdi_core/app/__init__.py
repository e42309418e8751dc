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

What a front end needs besides the jobs comes from here too, so that the
add-on imports the engine through this module alone (and the lens report,
``optics.report``): ``lenses`` (the catalogue's folders, a lens read, a
camera's stop, a Zemax import, the thumbnails), ``camera`` (the pinhole
camera of a render and its depth conventions), ``images`` and ``rawexr``
(pixels in and out), ``errors`` (the one family of errors and the words
they are shown in), ``RenderRequest``, ``PSFSettings``, ``SourceWords``
(how a PSF source's message names files and lenses), the correction rule
(``choose_correction``, ``shipped_model``) and the network loader
(``load_dacn``; ``TORCH_VERSION``, ``TorchMissingError``).

Units: depths in metres, lengths on the sensor in mm, positions in pixels.
"""
from .. import errors
from ..caches import clear as clear_caches, sizes as cache_sizes
from ..errors import DcdiError, InputRangeError, TorchMissingError, in_words
from ..io import images, rawexr
from ..models import TORCH_VERSION
from ..psf.compute import PSFSettings
from ..psf.sources import SourceWords
from ..render import camera
from ..render.request import RenderRequest
from . import lenses
from ..control import Cancelled, Control
from ..psf.budget import DEFAULT_DB as DEFAULT_BUDGET_DB
from ..psf.sources import PREVIEW_TRACE, PSFRequest, PSFSourceResult, open_source
from .correction import CorrectRequest, CorrectResult, correct, prepare
from .correction import choose as choose_correction
from .correction_rule import shipped_model
from .frame import CaptureFrame, capture_frame
from .pipeline import DofRequest, DofResult, dof
from .render import BokehRequest, BokehResult, SimulateRequest, SimulateResult, bokeh, simulate
from .sources import SourceCache

__all__ = ["Cancelled", "Control", "PSFRequest", "PSFSourceResult", "SourceCache", "open_source", "PREVIEW_TRACE",
           "DEFAULT_BUDGET_DB",
           "SimulateRequest", "SimulateResult", "simulate", "BokehRequest", "BokehResult", "bokeh",
           "CorrectRequest", "CorrectResult", "correct", "prepare", "CaptureFrame", "capture_frame",
           "DofRequest", "DofResult", "dof", "clear_caches", "cache_sizes",
           "errors", "DcdiError", "InputRangeError", "TorchMissingError", "in_words", "images", "rawexr",
           "TORCH_VERSION", "PSFSettings", "SourceWords", "camera", "RenderRequest", "lenses", "choose_correction",
           "shipped_model", "load_dacn"]


def load_dacn(path, weights: str = "ema", device: str = "cpu"):
    """(model, info) of a DACN file or run folder (``models.dacn.correct.
    load_dacn``); imports torch: ``TorchMissingError`` (with the command that
    installs it) where there is none."""
    from ..models.dacn.correct import load_dacn as load
    return load(path, weights=weights, device=device)
