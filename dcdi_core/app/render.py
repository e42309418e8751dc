"""The render jobs a user asks for: a lens's aberrations on an all-in-focus
RGB-D image (:func:`simulate`) and a lens's depth of field on it
(:func:`bokeh`). Both front ends (the `dcdi` command, the Blender add-on)
build a request, call the job and translate the result; the decisions (which
PSFs, which bins, what the user is told) are made here once.

Units: depths in metres from the lens's first vertex, lengths on the sensor
in mm, image positions in pixels (row, col).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputRangeError, RenderError
from ..render.inputs import depth_counts, depth_notes
from ..render.request import RenderRequest
from ..control import Cancelled, Control
from .records import recorded_defaults
from .sources import SourceCache
from ..psf.sources import PSFRequest, PSFSourceResult, ensure_bins, open_source
from ..psf.sampling import snap_focus


def _array(name: str, value, ndim: int):
    a = np.asarray(value, dtype=np.float32)
    if a.ndim != ndim or (ndim == 3 and a.shape[2] != 3):
        raise InputRangeError(name, a.shape, "(H, W, 3) linear RGB" if ndim == 3 else "(H, W) metres")
    return a


def _psf_request(psf: PSFRequest, render: RenderRequest, settings) -> PSFRequest:
    """The job's PSF request: the plan's settings, the explicit kernel of a render that does not fit one."""
    return replace(psf, settings=settings, fit_kernel=render.fit_kernel,
                   kernel_size=None if render.fit_kernel else settings.kernel_size)


def _source(lens, geometry, psf: PSFRequest, cache: SourceCache | None, fit_depth_m, control):
    chosen = cache.chosen(lens, geometry, psf) if cache is not None else None
    return open_source(lens, geometry, psf, fit_depth_m=fit_depth_m, control=control, chosen=chosen)


# the knobs' values in a request: the settings' rays and wavelengths, the request's field step
def _knob(psf: PSFRequest, name: str):
    return psf.field_step_px if name == "field_step_px" else getattr(psf.settings, name)


def widest_blur_px(lens, pixel_pitch_mm: float, focus_m, depth_m) -> float | None:
    """The widest thin-lens defocus blur (diameter, px) among the valid
    depths of ``depth_m`` (metres; None: none) with the lens focused at
    ``focus_m`` (metres; None: as prescribed, taken as infinity)."""
    if depth_m is None:
        return None
    d = np.asarray(depth_m, np.float64)
    d = d[d > 0]
    if d.size == 0:
        return None
    from ..psf.library import LibraryGrid
    from ..psf.sampling import blur_px_per_diopter
    grid = LibraryGrid()
    near = max(float(d.min()), grid.near_m)
    far = float(d.max())
    inv = [1.0 / near, 0.0 if far >= grid.far_m else 1.0 / far]
    f = 0.0 if focus_m is None or not math.isfinite(float(focus_m)) else 1.0 / float(focus_m)
    try:
        per = blur_px_per_diopter(lens, pixel_pitch_mm)
    except (ValueError, ZeroDivisionError, ArithmeticError):
        return None
    px = per * max(abs(x - f) for x in inv)
    return px if math.isfinite(px) else None


def budgeted(lens, geometry, psf: PSFRequest, cache: SourceCache | None = None, fixed: dict | None = None,
             depth_m=None):
    """(the request with the PSF work its error budget needs, the plan or
    None): where ``psf.max_error_db`` is set and the source that serves it
    makes PSFs (a ray map, an OLF in ray space or a trace), the rays, wavelengths and field step
    the planner (``psf.budget``) chooses for this lens at ``geometry``'s
    pitch, the knobs in ``psf.fixed`` kept; a stored source (basis, OLF)
    serves as it is (None). ``fixed``: the render's own knobs the job
    gives (``budget.KNOBS``: the bokeh's coarse rule and kernel crop; a
    simulation fixes both, having neither). ``depth_m``: the depths the
    job blurs, whose widest blur sets the fewest rays (``budget.min_rays``)."""
    if psf.max_error_db is None:
        return psf, None
    from ..psf.budget import plan as plan_budget
    from ..psf.sources import choose
    src = cache.chosen(lens, geometry, psf) if cache is not None else choose(lens, geometry, psf)
    if not src.plans:
        return psf, None
    given = {k: _knob(psf, k) for k in psf.fixed if k in ("pupil_samples", "n_wavelengths", "field_step_px")}
    blur = widest_blur_px(lens, geometry.pixel_pitch_mm, psf.focus_m, depth_m)
    q = plan_budget(lens, geometry.pixel_pitch_mm, psf.max_error_db, {**given, **(fixed or {})}, blur_px=blur)
    if not q.planned:
        return psf, q
    step = psf.field_step_px if "field_step_px" in psf.fixed else q.field_step_px
    # the plan replaces the preview's fixed lighter trace (``psf.sources.PREVIEW_TRACE``)
    return replace(psf, settings=q.apply(psf.settings), field_step_px=step, preview=False), q


def _mark_planned(src: PSFSourceResult, q) -> None:
    """A source whose PSFs the budget planned says so (``quality`` 'planned')."""
    if q is not None and q.planned:
        src.quality = "planned"


def _quality_info(q) -> dict:
    return {} if q is None else {"quality": q.as_dict()}


# ------------------------------------------------------------------ simulate
@dataclass(frozen=True)
class SimulateRequest:
    """The aberrations of ``lens`` on an all-in-focus ``image`` (H, W, 3)
    float32 linear with ``depth_m`` (H, W) metres (None only with
    ``render.fixed_depth_m``). ``render``: the image on the sensor (pixel
    pitch, over-scan, axis), the PSF settings (their focus moves the
    sensor), patch, interpolation, noise and its seed, a fixed depth, a
    perturbation of the prescription (``render.request.RenderRequest``).
    ``psf``: which PSFs (:class:`PSFRequest`). ``distortion``: apply the
    lens's distortion. ``accelerator``: None (numpy) or 'torch'.
    ``image_name``: how messages name the image."""

    image: np.ndarray
    depth_m: np.ndarray | None
    lens: object
    render: RenderRequest | None = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    distortion: bool = True
    accelerator: str | None = None
    image_name: str = "the image"


@dataclass
class SimulateResult:
    """``image``: the capture (H, W, 3) float32 on the sensor's frame;
    ``sharp``: the ideal image distorted alike (an aligned pair); ``depth_m``:
    the depth on the sensor (NaN where the lens images nothing); ``geometry``:
    the frame on the sensor; ``lens``: the lens used (perturbed if asked);
    ``source``: the PSFs; ``info``: the simulation's figures; ``perturbation``:
    the perturbation's record; ``record``: what a capture file remembers;
    ``notes``: lines for the user (depth pixels masked or clamped)."""

    image: np.ndarray
    sharp: np.ndarray
    depth_m: np.ndarray
    geometry: object
    lens: object
    source: PSFSourceResult
    info: dict
    perturbation: dict | None
    record: object
    seconds: dict
    notes: list = field(default_factory=list)


# a pixel is lit where a channel of the scene exceeds LIT (linear), black where no channel of the result exceeds
# BLACK: what no ray reaching it leaves (the result of a lens that passes light is never that dark where it is lit)
LIT, BLACK = 1e-4, 1e-7
DARK_NOTE_SHARE = 0.005   # the share of the lit frame left black that is said


def check_light(scene: np.ndarray, result: np.ndarray, lens, what: str, depth_m=None, *,
                input_lit: bool = True) -> str | None:
    """Whatever the PSFs' source: refuse a result that is black wherever
    the ``scene`` is lit (no ray of ``lens`` reaches the sensor: a clear
    aperture that passes nothing, a blur no kernel holds); the note of the
    share of the lit frame left black where part of it is (None: none).
    ``scene``: the sharp image on the result's frame (a simulation's is
    moved where the lens puts it: its corners beyond the input are black
    there too, and not counted); ``input_lit``: whether the input image
    has light at all (a frame onto which nothing of it was mapped is
    black too). ``depth_m``: the depth on that frame; its invalid pixels
    (said by the depth's own notes) are not counted."""
    if scene.shape != result.shape:
        return None
    lit = scene.max(axis=-1) > LIT
    if input_lit and not lit.any():
        raise RenderError(f"no light of {what} reaches the sensor through {getattr(lens, 'id', 'the lens')}: the "
                          "picture would be black (no ray maps the image onto the sensor)")
    if depth_m is not None and depth_m.shape == lit.shape:
        lit &= np.isfinite(depth_m) & (depth_m > 0)
    n = int(lit.sum())
    if n == 0:
        return None
    dark = int((np.abs(result).max(axis=-1) <= BLACK)[lit].sum())
    name = getattr(lens, "id", "the lens")
    if dark == n:
        raise RenderError(f"no light of {what} reaches the sensor through {name}: the picture would be black (no "
                          "ray passes the lens at these fields and depths: a clear aperture or a stop that passes "
                          "nothing?)")
    share = dark / n
    if share < DARK_NOTE_SHARE:
        return None
    return (f"{share:.1%} of {what}'s lit pixels are black through {name}: no ray reaches them (fields the lens "
            "vignettes wholly, or a blur wider than its kernels hold)")


def simulate(request: SimulateRequest, control: Control | None = None, *,
             cache: SourceCache | None = None) -> SimulateResult:
    """Run a :class:`SimulateRequest` (progress: 'PSFs', then 'simulating';
    cancel while PSFs are traced). ``cache``: keeps PSF sources between jobs."""
    from ..render.simulate import LensSimulator, SimulateOptions
    control = control or Control()
    img = _array("image", request.image, 3)
    depth = None if request.depth_m is None else _array("depth_m", request.depth_m, 2)
    render = request.render or RenderRequest(request.lens)
    if depth is None and render.fixed_depth_m is None:
        raise InputRangeError("depth_m", None, "the scene's depth map (H, W) metres, or a fixed depth")
    lens, perturbation = request.lens, None
    if render.perturb_seed is not None:
        from ..optics.perturb import perturb_lens
        lens, perturbation = perturb_lens(lens, seed=render.perturb_seed, fraction=render.perturb_fraction)
    t0 = time.perf_counter()
    plan = render.plan(*img.shape[:2], image=request.image_name)
    from ..render.convolve import ConvolveOptions
    psf, quality = budgeted(lens, plan.geometry, _psf_request(request.psf, render, plan.settings), cache,
                            {"coarse_blur": None, "support_eps": ConvolveOptions().support_eps},
                            depth if render.fixed_depth_m is None else np.array([render.fixed_depth_m]))
    if quality is not None:
        control.say(f"PSFs planned for {quality.budget_db:g} dB: {quality.why}")
        plan = replace(plan, settings=quality.apply(plan.settings))
    # the kernel grows to hold the PSFs this depth map needs (a basis's or an
    # OLF's kernels hold their energy over the whole depth range)
    src = _source(lens, plan.geometry, psf, cache, depth if render.fixed_depth_m is None else None, control)
    _mark_planned(src, quality)
    options = SimulateOptions(geometry=plan.geometry, source_geometry=plan.source_geometry, settings=plan.settings,
                              response=psf.response, patch=render.patch, distortion=request.distortion,
                              interpolation=render.interpolation, accelerator=request.accelerator)
    sim = LensSimulator(lens, options, library=src.library, progress=control.counter("PSFs"))
    t1 = time.perf_counter()
    control.report("simulating", 0, 1)
    depth_in = depth if depth is not None else np.full(img.shape[:2], render.fixed_depth_m, np.float32)
    r = sim(img, depth_in, fixed_depth_m=render.fixed_depth_m, noise=render.noise_settings, seed=render.seed)
    seconds = {"psfs": t1 - t0, "simulation": time.perf_counter() - t1}
    counts, notes = {}, []
    if render.fixed_depth_m is None:
        counts = depth_counts(depth, src.library.grid.near_m)
        notes = depth_notes(counts, f"the depth map of {request.image_name}",
                            "each takes its patch's blur, a patch with none is left sharp")
    if render.noise_settings is None:                 # (noise lifts a black pixel off zero)
        dark = check_light(r.sharp, r.image, lens, request.image_name, r.depth,
                           input_lit=bool((img.max(axis=-1) > LIT).any()))
        notes += [dark] if dark else []
    from .records import simulated_record
    extra = {} if render.fixed_depth_m is None else {"fixed_depth_m": float(render.fixed_depth_m)}
    if getattr(lens, "iris", ""):
        extra["iris"] = lens.iris                      # stopped down ('f/4, 6 blades'): optics.aperture
    if perturbation is not None:
        extra["perturb_seed"] = int(render.perturb_seed)
    record = simulated_record(lens, plan.geometry, focus_distance_m=plan.settings.focus_distance_m,
                              psf_source=src.kind, noise=render.noise_settings, seed=render.seed,
                              distortion=request.distortion, extra=extra)
    return SimulateResult(r.image, r.sharp, r.depth, plan.geometry, lens, src,
                          {**r.info, **counts, **_quality_info(quality)}, perturbation, record, seconds, notes)


# ------------------------------------------------------------------ bokeh
@dataclass(frozen=True)
class BokehRequest:
    """The depth of field of ``lens`` on an all-in-focus ``image`` (H, W, 3)
    float32 linear with ``depth_m`` (H, W) metres.

    What is sharp, at least one of: ``keep`` (near, far) metres kept exactly
    sharp, ``focus_m`` the lens focused there (metres, or 'prescribed': the
    lens as its prescription stands). ``render``: the image on the sensor
    and the PSF settings (``render.request.RenderRequest``; its PSF focus
    must be unset: the focus is ``focus_m``). ``occlusion``: the
    occlusion-aware layers (False: the plain patch-wise blur);
    ``distortion``: also the lens's distortion; ``multires`` / ``max_level``:
    the multi-resolution blur (``render.bokeh.BokehOptions``);
    ``exact_layers``: every depth layer as the equal-width split makes it,
    at the image's patches with the tent (no merging, no wider patches:
    ``BokehOptions``' interp_eps and seam_tol None). ``coarse_blur``: the
    coarse layers' rule (``BokehOptions``; None: planned by the PSF
    request's error budget where it has one, else none). ``support_eps``:
    the energy a kernel's crop may leave out (``BokehOptions``; None:
    planned by the budget, else ``BokehOptions``' default). ``psf``:
    which PSFs (:class:`PSFRequest`; ``preview``: a lighter trace).
    ``recorded``: what the image file remembers
    (``io.capture_record.CaptureRecord``; ``records.recorded_defaults``)."""

    image: np.ndarray
    depth_m: np.ndarray
    lens: object
    keep: tuple[float, float] | None = None
    focus_m: float | str | None = None
    render: RenderRequest | None = None
    occlusion: bool = True
    distortion: bool = False
    multires: float | None = None
    max_level: int | None = None
    exact_layers: bool = False
    coarse_blur: float | None = None
    support_eps: float | None = None
    psf: PSFRequest = field(default_factory=PSFRequest)
    recorded: object = None
    image_name: str = "the image"


@dataclass
class BokehResult:
    """``image`` (H, W, 3) float32 on the sensor's frame; ``sharp`` / ``depth_m``:
    the input moved onto the sensor (None when it was not moved); ``geometry``;
    ``source``: the PSFs; ``info``; ``notes``: lines for the user (a focus
    where nothing in view lies)."""

    image: np.ndarray
    sharp: np.ndarray | None
    depth_m: np.ndarray | None
    geometry: object
    source: PSFSourceResult
    info: dict
    notes: list
    seconds: dict


# a depth blurred less than this (thin-lens blur diameter, px) is in focus: within the lens's depth of field
IN_FOCUS_PX = 2.0


def _focus_note(depth, keep, lens=None, pixel_pitch_mm=None, focus_m=None) -> str | None:
    """What the user is told where nothing in view is in focus: nothing lies
    in the kept range, nor within the lens's depth of field about the focus
    (a thin-lens blur under ``IN_FOCUS_PX``; with a lens and pitch given):
    the sharpest depth in view and its blur. None where something is sharp."""
    if keep is None:
        return None
    if int(((depth >= keep[0]) & (depth <= keep[1])).sum()):
        return None
    valid = depth[depth > 0]
    finite = valid[np.isfinite(valid)]
    seen = f"{finite.min():.2f}-{finite.max():.2f} m" if finite.size else "only background (infinity)"
    where = f"the kept range {keep[0]:.2f}-{keep[1]:.2f} m" if keep[1] > keep[0] else f"the focus {keep[0]:.2f} m"
    sharpest = None
    if lens is not None and pixel_pitch_mm is not None and valid.size:
        inv = np.unique(np.where(np.isfinite(valid), 1.0 / valid, 0.0))
        f = 0.0 if focus_m is None or not math.isfinite(float(focus_m)) else 1.0 / float(focus_m)
        i = int(np.argmin(np.abs(inv - f)))
        blur = widest_blur_px(lens, pixel_pitch_mm, focus_m, np.array([1.0 / inv[i] if inv[i] > 0 else np.inf]))
        if blur is not None and blur < IN_FOCUS_PX:
            return None                      # something lies within the lens's depth of field
        if blur is not None:
            d = "infinity" if inv[i] == 0 else f"{1.0 / inv[i]:.2f} m"
            sharpest = f"the sharpest, at {d}, is blurred {blur:.0f} px"
    return (f"nothing in view is in focus: nothing lies at {where} (depths in view: {seen}"
            + (f"; {sharpest}" if sharpest else "") + "): everything is out of focus")


def bokeh_plan(request: BokehRequest, shape):
    """(the render request, its plan (``render.request.RenderPlan``), notes)
    a bokeh of ``shape`` (rows, cols) runs on, with what the image's record
    says."""
    render, notes = recorded_defaults(request.render, request.lens, request.recorded, tuple(shape),
                                      request.image_name, focus=False, lens_bound=False)
    render = render or RenderRequest(request.lens)
    return render, render.plan(*shape, image=request.image_name), notes


def bokeh(request: BokehRequest, control: Control | None = None, *, cache: SourceCache | None = None,
          plan=None) -> BokehResult:
    """Run a :class:`BokehRequest`. The PSF bins the scene blurs are built
    first (progress 'PSFs', cancel between bins), then the layers (progress
    'depth layers', cancel between them). The kernel grows to hold the blur
    of the frame's depth bins (the kept ones too: the layers' patches at a
    sharp subject's edge take their kernels from its bins). ``plan``: the
    request's :func:`bokeh_plan` where the caller made it already (a DCDI
    job plans its target once)."""
    from ..render.bokeh import BokehOptions
    from ..render.bokeh import bokeh as render_bokeh
    from ..render.base import Cancelled as RenderCancelled
    control = control or Control()
    img = _array("image", request.image, 3)
    depth = _array("depth_m", request.depth_m, 2)
    t0 = time.perf_counter()
    render, plan, notes = plan or bokeh_plan(request, img.shape[:2])
    # nearby focus distances share PSFs where the request allows it (``psf.sampling``)
    focus_m = snap_focus(request.lens, request.focus_m, plan.geometry.pixel_pitch_mm, request.psf.focus_tolerance_px)
    options = BokehOptions(keep=request.keep, focus_m=focus_m, geometry=plan.geometry,
                           source_geometry=plan.source_geometry, distortion=request.distortion,
                           interpolation=render.interpolation, patch=render.patch, occlusion=request.occlusion,
                           settings=plan.settings, response=request.psf.response, fit_kernel=render.fit_kernel,
                           multires=request.multires, max_level=request.max_level, coarse_blur=request.coarse_blur,
                           **({} if request.support_eps is None else {"support_eps": request.support_eps}),
                           **(dict(interp_eps=None, seam_tol=None) if request.exact_layers else {}))
    psf = _psf_request(request.psf, render, plan.settings).focused(options.focus_distance_m)
    layered = request.occlusion and request.multires is None
    fixed = {"coarse_blur": request.coarse_blur} if request.coarse_blur is not None or not layered else {}
    if request.support_eps is not None:
        fixed["support_eps"] = request.support_eps
    keep = options.keep
    blurred = depth[(depth > 0) & ~((depth >= keep[0]) & (depth <= keep[1]))] if keep is not None else depth[depth > 0]
    psf, quality = budgeted(request.lens, plan.geometry, psf, cache, fixed, blurred)
    if quality is not None:
        control.say(f"PSFs planned for {quality.budget_db:g} dB: {quality.why}")
        # the large blur's and the coarse layers' PSFs are made with the same planned settings
        if quality.planned:
            options = replace(options, settings=quality.apply(options.settings), coarse_blur=quality.coarse_blur,
                              support_eps=quality.support_eps)
    # the kernel holds the blur of every bin the layers may take, the kept depths' too: a patch at a sharp
    # subject's edge interpolates from their bins (a fast lens's halo near focus: the Summicron's needs 49 px)
    valid = depth[depth > 0]
    src = _source(request.lens, plan.geometry, psf, cache, valid if blurred.size else None, control)
    _mark_planned(src, quality)
    lib = src.library
    # a kernel that clips is the large blur's to answer (render.bokeh): warned only where it did not
    quiet = getattr(lib, "quiet_clipping", None)
    if quiet is not None:
        lib.quiet_clipping = True
    try:
        ensure_bins(lib, blurred, control)
        t1 = time.perf_counter()
        control.report("depth layers", 0, 1)
        # progress: the PSFs a large blur traces at a coarser pitch (render.bokeh's large_blur), if any
        r = render_bokeh(img, depth, request.lens, options, library=lib, cancelled=control.cancelled,
                         progress=control.counter("PSFs"), layer_progress=control.counter("depth layers"))
    except RenderCancelled:
        raise Cancelled("cancelled") from None
    finally:
        if quiet is not None:
            lib.quiet_clipping = quiet
    # a large blur answers the image-pitch kernel's clipping, unless its own coarse kernels clip too
    clipped = r.info.get("large_blur_clipped") if r.info.get("large_blur_factor") else \
        (None if quiet is None else lib.clip_text())
    if clipped and not r.info.get("large_blur_factor"):
        lib.warn_if_clipped()
    note = _focus_note(depth, keep, request.lens, plan.geometry.pixel_pitch_mm, options.focus_distance_m)
    if r.info.get("large_blur_factor"):
        f = r.info["large_blur_factor"]
        notes.append(f"{r.info['large_blur_layers']} depth layer(s) blurred beyond the {src.library.kernel_size}-px "
                     f"kernel were rendered at 1/{f} of the resolution with PSFs made at {f} x the pixel pitch by the same source "
                     + (f"(still clipped: {clipped})" if clipped else "(their blur whole, not clipped)"))
    seconds = {"psfs": t1 - t0, "bokeh": time.perf_counter() - t1}
    dark = check_light(img if r.sharp is None else r.sharp, r.image, request.lens, request.image_name,
                       depth if r.depth is None else r.depth, input_lit=bool((img.max(axis=-1) > LIT).any()))
    notes += [dark] if dark else []
    counts = depth_counts(depth, src.library.grid.near_m)
    notes += depth_notes(counts, f"the depth map of {request.image_name}", "left sharp")
    if focus_m != request.focus_m:
        counts["focus_used_m"] = float(focus_m)          # rounded within the request's focus tolerance
    extra = {"clipped": clipped} if clipped else {}
    return BokehResult(r.image.astype(np.float32), r.sharp, r.depth, plan.geometry, src,
                       {**r.info, **counts, **_quality_info(quality), **extra}, notes + ([note] if note else []),
                       seconds)
