"""The add-on's logic without bpy: the lens catalogue and readout, preview
size, the kept range, and the jobs run on a worker thread in the UI (the
bokeh, the simulation, its correction: deconvolution without torch, or a
network where torch imports).
Everything optical is a call into ``dcdi_core`` (the camera and depth
conversion: ``dcdi_core.render.camera``).

Units: depths and distances in metres (from the lens's first vertex unless
said otherwise), lens lengths in mm, angles in degrees.
"""
from __future__ import annotations

import importlib.util
import math
import os
import sys
import tomllib
import warnings
import zlib
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .core import core

class Cancelled(Exception):
    """The user pressed Esc while the PSFs were being built."""


class BokehInputError(ValueError):
    """Something about the scene or the settings that makes the bokeh impossible;
    the message says what to change."""


# ------------------------------------------------------------------ lenses
@dataclass(frozen=True)
class LensEntry:
    """One lens file the panel offers."""

    id: str
    name: str
    path: str
    number: int          # stable enum number (crc32 of the id), so saved files keep their choice


# the render request's settings by the names the panel shows (render.request.RenderRequest's labels)
PANEL_LABELS = {"patch": "Patch Size", "interpolation": "Interpolation", "seed": "Seed", "noise": "Sensor Noise",
                "wavelength_nm": "Wavelength", "image_pixel_pitch_mm": "pixel pitch", "sensor_size": "sensor size",
                "axis_px": "optical axis", "pixel_pitch_mm": "pixel pitch", "fixed_depth_m": "fixed depth",
                "perturb_fraction": "perturbation"}


def lens_catalogue(extra_dirs=()) -> list[LensEntry]:
    """Every ``*.toml`` in dcdi_core's lens folders ($DCDI_LENS_PATH, the
    bundled ``lenses/``) and in ``extra_dirs`` (the add-on's imported lenses);
    the first file of an id wins. A file whose name cannot be read is still
    listed (its error shows when it is chosen)."""
    dirs = list(core("optics.lens").lens_dirs()) + [Path(d) for d in extra_dirs if d and Path(d).is_dir()]
    seen, out = set(), []
    for d in dirs:
        for p in sorted(Path(d).glob("*.toml")):
            if p.stem in seen:
                continue
            seen.add(p.stem)
            out.append(LensEntry(p.stem, _lens_name(p), str(p), lens_number(p.stem)))
    return out


def lens_number(lens_id: str) -> int:
    """The enum number of a lens id: crc32, so it does not change when lenses are added."""
    return zlib.crc32(lens_id.encode()) & 0x7FFFFFFF


_NAME_CACHE: dict = {}


def _lens_name(p: Path) -> str:
    key = (str(p), p.stat().st_mtime_ns)
    if key not in _NAME_CACHE:
        try:
            with open(p, "rb") as f:
                name = str(tomllib.load(f).get("name") or p.stem)
        except (OSError, tomllib.TOMLDecodeError):
            name = f"{p.stem} (unreadable file)"
        _NAME_CACHE[key] = name
    return _NAME_CACHE[key]


_LENS_CACHE: dict = {}


def load_lens_cached(path: str):
    """The Lens of a TOML file, cached by path and modification time; raises
    dcdi_core's LensFileError (naming file, surface and field) for a broken file."""
    key = (path, os.stat(path).st_mtime_ns)
    if key not in _LENS_CACHE:
        _LENS_CACHE[key] = core("optics.lens").Lens.from_toml(path)
    return _LENS_CACHE[key]


_READOUT_CACHE: dict = {}


def lens_readout(path: str) -> dict:
    """Focal length (paraxial EFL, mm), F-number (paraxial), diagonal field of
    view (real chief ray at field 1, degrees), entrance pupil position (mm
    behind the first vertex) and sensor semi-diagonal (mm). Cached by file
    and modification time (the real-ray field angle costs ~0.1 s)."""
    key = (path, os.stat(path).st_mtime_ns)
    if key not in _READOUT_CACHE:
        lens = load_lens_cached(path)
        fo = core("optics.paraxial").first_order(lens)
        half = float(core("optics.analysis").real_field_angle_deg(lens, [1.0])[0])
        _READOUT_CACHE[key] = {
            "id": lens.id, "name": lens.name,
            "focal_length_mm": float(fo.effective_focal_length_mm),
            "f_number": float(fo.f_number),
            "field_of_view_deg": 2.0 * half if half > 0 else None,
            "entrance_pupil_mm": float(fo.entrance_pupil_position_mm),
            "sensor_semi_diagonal_mm": float(lens.sensor.semi_diagonal_mm),
        }
    return _READOUT_CACHE[key]


# the lens list's thumbnails: PSFs at these fields (rows) and depths (columns,
# metres from the lens; inf: infinity), the lens as prescribed
THUMBNAIL_FIELDS = (0.0, 0.5, 0.9)
THUMBNAIL_DEPTHS_M = (1.0, 3.0, math.inf)
THUMBNAIL_TILE_PX = 31


def psf_thumbnail(lens, tile: int = THUMBNAIL_TILE_PX) -> np.ndarray:
    """A grid of the lens's RGB PSFs (THUMBNAIL_FIELDS x THUMBNAIL_DEPTHS_M),
    each tile ``tile`` px at the pixel pitch of a 600-px-diagonal image on
    its sensor, scaled to its own peak and gamma-encoded (1/2.2) so that
    halos show: float32 (H, W, 3) in [0, 1], rows top to bottom, 1-px
    gaps. Quick settings (32 x 32 pupil rays, 5 wavelengths): a picture of
    the lens's character, not its exact PSFs."""
    compute = core("psf.compute")
    pitch = 2.0 * lens.sensor.semi_diagonal_mm / 600.0
    settings = compute.PSFSettings(kernel_size=tile, pupil_samples=32, n_wavelengths=5, pixel_pitch_mm=pitch)
    nf, nd = len(THUMBNAIL_FIELDS), len(THUMBNAIL_DEPTHS_M)
    out = np.zeros((nf * (tile + 1) - 1, nd * (tile + 1) - 1, 3), np.float32)
    for i, f in enumerate(THUMBNAIL_FIELDS):
        for j, d in enumerate(THUMBNAIL_DEPTHS_M):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")         # a PSF larger than the tile is clipped: a picture
                k = compute.psf(lens, depth_m=d, field=f, settings=settings).psf
            img = np.moveaxis(np.nan_to_num(k, nan=0.0), 0, -1)
            peak = float(img.max())
            tile_img = (img / peak) ** (1.0 / 2.2) if peak > 0 else img
            out[i * (tile + 1):i * (tile + 1) + tile, j * (tile + 1):j * (tile + 1) + tile] = tile_img
    return out


def import_zemax(zmx_path: str, out_dir: str) -> str:
    """Convert a Zemax .zmx file to a lens TOML in ``out_dir`` (validated
    before anything is written; written atomically); returns the TOML path."""
    zemax = core("optics.zemax")
    d = zemax.read_zmx(zmx_path)
    core("optics.lens").Lens.from_dict(d, zmx_path)      # raises with file / surface / field
    out = Path(out_dir) / f"{d['id']}.toml"
    zemax.write_toml(d, out)
    return str(out)


# ------------------------------------------------------------------ scene -> job
def preview_shape(res_x: int, res_y: int, aspect_x: float, aspect_y: float, long_side: int) -> tuple[int, int]:
    """(height, width) of the preview: the render's displayed aspect with its
    long side ``long_side`` pixels (at least 8 px each way)."""
    if long_side < 8:
        raise BokehInputError(f"preview resolution {long_side} px: allowed 8 and up")
    w_disp, h_disp = res_x * aspect_x, res_y * aspect_y
    if w_disp >= h_disp:
        return max(8, round(long_side * h_disp / w_disp)), long_side
    return long_side, max(8, round(long_side * w_disp / h_disp))


def keep_range(focus_m: float, front_m: float, behind_m: float) -> tuple[float, float]:
    """The depths kept sharp, metres: [focus - front, focus + behind] (near end at least 1 mm)."""
    if not (focus_m > 0 and math.isfinite(focus_m)):
        raise BokehInputError(f"focus distance {focus_m:.4g} m: it must be positive and finite "
                              "(is the focus object behind the camera?)")
    if front_m < 0 or behind_m < 0:
        raise BokehInputError(f"kept range in front {front_m} m / behind {behind_m} m: both must be >= 0")
    return max(focus_m - front_m, 1e-3), focus_m + behind_m


def _psf_progress(progress, cancelled):
    """The ``progress(done, total)`` a PSF build calls: raises
    :class:`Cancelled` when ``cancelled()`` says so, else reports stage 'PSFs'."""
    def report(done, total):
        _check_cancel(cancelled)
        if progress is not None:
            progress("PSFs", done / max(total, 1))
    return report


def _check_cancel(cancelled) -> None:
    if cancelled is not None and cancelled():
        raise Cancelled()


# The viewport preview's PSFs where they must be traced (no shipped basis or
# OLF holds the request, e.g. a minimalist lens refocused): fewer pupil rays
# and wavelengths, a proxy of the render's (docs/addon.md gives its error and
# time against the full trace); Apply Lens Bokeh and renders trace in full.
PREVIEW_TRACE = {"pupil_samples": 24, "n_wavelengths": 9}


def run_bokeh(image, depth, lens, *, focus_m: float, keep: tuple[float, float], patch: int = 16,
              refocus: bool = True, progress=None, cancelled=None, preview: bool = False):
    """The lens's depth of field on an all-in-focus (H, W, 3) float32 linear
    image with depth (H, W) metres: the lens focused at ``focus_m`` (or, with
    ``refocus`` False, as its prescription stands), depths in ``keep`` exactly
    sharp. The PSFs come from the lens's shipped PSF basis or the shipped
    Omni-Lens-Field where one covers the lens and the request, else they are
    traced (``psf_source``, the CLI's rule): info's ``psf_source`` ('basis',
    'olf' or 'trace') and
    ``psf_source_message`` (which and why). ``progress(stage, fraction)`` is
    called while the PSF bins the scene needs are built (traced ones cached in
    ~/.cache/dcdi, or $DCDI_CACHE_DIR) and before the convolution;
    ``cancelled()`` returning True stops the PSF build or the convolution
    (between its layers) with :class:`Cancelled`. A focus where nothing in
    view lies blurs everything; info's ``focus_note`` says so ('' otherwise).
    ``preview``: PSFs that must be traced are traced with ``PREVIEW_TRACE``
    (info's ``psf_quality`` 'preview'). Returns (image, info)."""
    sim = core("render.simulate")
    settings = replace(core("psf.compute").PSFSettings(), focus_distance_m=float(focus_m) if refocus else None)
    # the same checked request as `dcdi bokeh` builds; messages name the panel's settings
    plan = core("render.request").RenderRequest(lens, psf=settings, patch=patch, labels=PANEL_LABELS).plan(
        image.shape[0], image.shape[1], "the render")
    geom = plan.geometry
    quality = "full"
    if preview and cached_psf_source(lens, geom.pixel_pitch_mm, settings).kind == "trace":
        settings, quality = replace(settings, **PREVIEW_TRACE), "preview"
    finite = depth[np.isfinite(depth) & (depth > 0)]
    kept = int(((depth >= keep[0]) & (depth <= keep[1])).sum())
    # a camera may focus on empty space: then everything in view is out of focus
    focus_note = ""
    if kept == 0:
        seen = (f"{finite.min():.2f}-{finite.max():.2f} m" if finite.size else "only background (infinity)")
        focus_note = (f"nothing in view lies in the kept range {keep[0]:.2f}-{keep[1]:.2f} m (depths in view: "
                      f"{seen}): everything is out of focus")
    report = _psf_progress(progress, cancelled)

    # The PSFs the scene needs are built first, so that progress and Esc work
    # here (the convolution that follows takes well under the build's time);
    # the kernel grows to hold the blur of the depths that get blurred. Each
    # patch gets the PSF at its mean inverse depth, which can fall in a bin no
    # single pixel touches: every bin between the nearest and farthest is built.
    blurred = depth[np.isfinite(depth) & (depth > 0) & ~((depth >= keep[0]) & (depth <= keep[1]))]
    blurred = np.concatenate([blurred, depth[np.isinf(depth) & (depth > 0)][:1]])
    src = cached_psf_source(lens, geom.pixel_pitch_mm, settings)
    lib = src.library or sim.open_library(lens, geom, settings, fit_depth_m=blurred if blurred.size else None,
                                          progress=report)
    if blurred.size:
        need = lib.bins_needed(blurred, clamp_near=True)
        lib.ensure(bins=np.arange(need.min(), need.max() + 1), progress=report)
    _check_cancel(cancelled)
    if progress is not None:
        progress("convolving", 1.0)
    try:
        res = sim.bokeh(image, depth, lens, sim.BokehOptions(keep=keep, geometry=geom, patch=patch), library=lib,
                        cancelled=cancelled)
    except sim.Cancelled:
        raise Cancelled() from None
    info = dict(res.info, focus_m=float(focus_m), keep_m=[float(keep[0]), float(keep[1])], refocus=bool(refocus),
                pixel_pitch_mm=float(geom.pixel_pitch_mm), psf_source=src.kind, psf_source_message=src.message,
                focus_note=focus_note, psf_quality=quality)
    return res.image.astype(np.float32), info


# ------------------------------------------------------------------ PSFs kept between jobs
# The PSF sources of the last few (lens file, pixel pitch, focus) requests:
# an Omni-Lens-Field library keeps the bins it computed, so the frames of an
# animation with one focus, or a preview refreshed after a change elsewhere,
# pay the PSFs once. Traced libraries live in the disk cache instead.
_SOURCES: "OrderedDict" = OrderedDict()
SOURCE_CACHE_SIZE = 6


def cached_psf_source(lens, pixel_pitch_mm: float, settings):
    """``runtime.library.psf_source`` for ``lens`` at ``pixel_pitch_mm`` (mm)
    with ``settings`` (their focus_distance_m the focus, None: as
    prescribed), kept for the next call with the same lens file (path and
    modification time), pitch and focus."""
    path = str(getattr(lens, "path", "") or "")
    mtime = os.stat(path).st_mtime_ns if path and os.path.exists(path) else None
    key = (lens.id, path, mtime, round(float(pixel_pitch_mm), 12), settings.focus_distance_m)
    if key in _SOURCES:
        _SOURCES.move_to_end(key)
        return _SOURCES[key]
    src = core("models.runtime.library").psf_source(lens, pixel_pitch_mm=pixel_pitch_mm, settings=settings,
                                                     focus_m=settings.focus_distance_m, labels=PSF_SOURCE_LABELS)
    _SOURCES[key] = src
    while len(_SOURCES) > SOURCE_CACHE_SIZE:
        _SOURCES.popitem(last=False)
    return src


def clear_psf_sources() -> None:
    """Drop the kept PSF sources (unregister)."""
    _SOURCES.clear()


# ------------------------------------------------------------------ Lens in Renders
# what a rendered frame gets: the depth of field (the bokeh, the panel's
# focus and kept range), or the whole lens (aberrations, distortion and
# defocus: the simulation focused at the focus distance)
RENDER_EFFECTS = ("dof", "lens")


@dataclass(frozen=True)
class FrameRequest:
    """What one rendered frame gets: ``effect`` (one of RENDER_EFFECTS), the
    focus (m from the lens's first vertex), the kept range (m) and whether
    the lens is refocused (the bokeh's), the lens's entrance pupil (mm
    behind its first vertex) and the scene's metres per unit (the Z pass's
    conversion)."""

    effect: str
    focus_m: float
    keep: tuple[float, float]
    refocus: bool
    entrance_pupil_mm: float
    metres_per_unit: float = 1.0

    def __post_init__(self):
        if self.effect not in RENDER_EFFECTS:
            raise BokehInputError(f"render effect {self.effect!r}: allowed {', '.join(RENDER_EFFECTS)}")
        keep_range(self.focus_m, 0.0, 0.0)           # the focus's own check
        if not (self.metres_per_unit > 0 and math.isfinite(self.metres_per_unit)):
            raise BokehInputError(f"unit scale {self.metres_per_unit}: it must be positive and finite")


def lens_frame(rgb, z, lens, request: FrameRequest, *, progress=None, cancelled=None):
    """A rendered frame through ``lens``: its Combined pass ``rgb`` (H, W, 3)
    float32 linear and planar Z pass ``z`` (H, W) scene units (Blender's
    1e10 for the background), as ``request`` says. Returns (image, depth
    metres from the lens's first vertex, info: the job's, with 'effect')."""
    depth = core("render.camera").depth_from_planar_z(z, request.entrance_pupil_mm, request.metres_per_unit)
    rgb = np.nan_to_num(np.asarray(rgb, np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    if request.effect == "dof":
        out, info = run_bokeh(rgb, depth, lens, focus_m=request.focus_m, keep=request.keep,
                              refocus=request.refocus, progress=progress, cancelled=cancelled)
    else:
        out, _, _, info = run_simulation(rgb, depth, lens, focus_m=request.focus_m, progress=progress,
                                         cancelled=cancelled)
    return out, depth, dict(info, effect=request.effect)


# ------------------------------------------------------------------ the DCDI round trip
def run_simulation(image, depth, lens, *, noise: bool = False, seed: int = 0, focus_m: float | None = None,
                   progress=None, cancelled=None):
    """The all-in-focus (H, W, 3) render with depth (H, W) metres as ``lens``
    (as prescribed, or with ``focus_m`` its sensor moved to focus there: `dcdi
    simulate --focus`) would have taken it: dcdi_core's depth-aware
    simulation (``render.simulate``: distortion, then patch-wise PSFs of
    field and depth; sensor noise if ``noise``, seeded by ``seed``), with
    PSFs from the shipped Omni-Lens-Field where it covers the lens, else
    traced (the bokeh's rule). ``progress`` / ``cancelled`` as
    :func:`run_bokeh` (cancel works while PSFs are traced). Returns (image,
    depth on the sensor (NaN where the lens images nothing), the image's
    geometry on the sensor, info): what :func:`run_correction` needs."""
    sim = core("render.simulate")
    settings = replace(core("psf.compute").PSFSettings(), focus_distance_m=None if focus_m is None else float(focus_m))
    plan = core("render.request").RenderRequest(lens, psf=settings, labels=PANEL_LABELS).plan(
        image.shape[0], image.shape[1], "the render")
    geom = plan.geometry
    src = cached_psf_source(lens, geom.pixel_pitch_mm, plan.settings)
    simulator = sim.LensSimulator(lens, geom, library=src.library, settings=plan.settings,
                                  fit_depth_m=depth if src.library is None else None,
                                  progress=_psf_progress(progress, cancelled))
    _check_cancel(cancelled)
    if progress is not None:
        progress("simulating", 1.0)
    res = simulator(image, depth, noise={} if noise else None, seed=int(seed) if noise else None)
    info = dict(res.info, lens=lens.id, pixel_pitch_mm=float(geom.pixel_pitch_mm), psf_source=src.kind,
                psf_source_message=src.message)
    return res.image.astype(np.float32), res.depth.astype(np.float32), geom, info


def torch_install_command(python: str | None = None) -> str:
    """The command that installs the PyTorch the engine is tested with into ``python`` (default: this one)."""
    return f'"{python or sys.executable}" -m pip install torch=={core("models").TORCH_VERSION}'


def torch_missing() -> str | None:
    """Why Correct cannot run here (no importable torch, with the install
    command), or None. Looks for torch without importing it."""
    try:
        found = importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):
        found = False
    return None if found else _torch_message()


def _torch_message(detail: str = "") -> str:
    return (f"Correct's Network method needs PyTorch in Blender's Python, which has none{detail}: install it "
            f"with {torch_install_command()} and restart Blender (Deconvolution runs without it)")


def correction_model_path(lens_id: str, given: str = "") -> Path:
    """The DACN file for ``lens_id``: ``given`` (an absolute path, an
    exported .npz or a run folder) if set, else the shipped
    ``dacn-<lens>.npz``; errors say which lenses have a shipped one."""
    if given:
        p = Path(given)
        if not p.exists():
            raise BokehInputError(f"correction model {str(p)!r}: no such file (give a DACN exported with "
                                  "`dcdi dacn export` (.npz), or leave it empty for the lens's shipped one)")
        return p
    pipeline = core("pipeline")
    p = pipeline.shipped_model("dacn", lens_id)
    if p is None:
        have = pipeline.shipped_lenses("dacn")
        raise BokehInputError(f"no shipped correction network (DACN) for lens {lens_id!r}: shipped for "
                              f"{', '.join(have) if have else 'no lens yet'}; choose one of those lenses or give "
                              "a Correction Model file (`dcdi dacn export`)")
    return p


_DACN_CACHE: dict = {}


def load_dacn_cached(path: Path):
    """(model, info) of ``models.correct.load_dacn``, cached by path and
    modification time; a missing torch is reported with the install command."""
    try:
        correct = core("models.dacn.correct")
    except core("models").TorchMissingError:
        raise BokehInputError(_torch_message()) from None
    except ImportError as e:                 # a torch that is there but does not import
        raise BokehInputError(_torch_message(f" that imports ({e})")) from None
    key = (str(path), os.stat(path).st_mtime_ns)
    if key not in _DACN_CACHE:
        _DACN_CACHE.clear()                  # one network at a time: they are the biggest thing held
        _DACN_CACHE[key] = correct.load_dacn(path)
    return _DACN_CACHE[key]


# ------------------------------------------------------------------ Correct Simulation
# what Correct can run: the lens's blur undone with its own PSFs (numpy, every
# Python), or a trained DACN (torch); Auto asks the engine's rule
METHODS = ("auto", "deconvolution", "network")
METHOD_NAMES = {"auto": "Auto", "deconvolution": "Deconvolution", "network": "Network"}
# the engine's names of the two corrections (pipeline.choose_correction), and the panel's words for its options
# (pipeline.CORRECTION_LABELS's; the PSF source has no setting in the panel: its options go unnamed,
# in Correct as in Apply Lens Bokeh, Simulate and Lens in Renders)
ENGINE_METHODS = {"deconv": "deconvolution", "dacn": "network"}
PSF_SOURCE_LABELS = {"psf_source": None, "basis": None, "olf": None}
CORRECTION_LABELS = {"method": "Method", "model": "Correction Model", "lens": "Lens", **PSF_SOURCE_LABELS}
# the sensor Simulate's Sensor Noise adds (render.noise.add_sensor_noise's defaults), electrons
SENSOR_FULL_WELL_E = 10000.0
SENSOR_READ_NOISE_E = 3.0


@dataclass(frozen=True)
class CorrectionChoice:
    """What Correct runs: ``method`` ('deconvolution' or 'network'), why
    (``reason``, for the panel and the report), and the network's file."""

    method: str
    reason: str
    model_path: Path | None = None


def choose_correction(requested: str, lens_id: str, pixel_pitch_mm: float, given_model: str = "") -> CorrectionChoice:
    """The method for ``requested`` ('auto', 'deconvolution' or 'network')
    on a simulation of ``lens_id`` at ``pixel_pitch_mm`` (mm per pixel on
    the sensor), with the panel's Correction Model file ``given_model`` (''
    for the lens's shipped network). Network asked for explicitly needs
    torch and a network (the messages say what to install, or which lenses
    have one). Auto is the engine's rule (``pipeline.choose_correction``:
    the network given, or the lens's shipped one where it is recorded
    better than the deconvolution and learned this pixel pitch; else the
    deconvolution), with the deconvolution where the rule picks a network
    and torch does not import: Auto never fails for want of torch."""
    if requested not in METHODS:
        raise BokehInputError(f"correction method {requested!r}: allowed {', '.join(METHODS)}")
    if requested == "deconvolution":
        return CorrectionChoice("deconvolution", "chosen in the panel")
    if requested == "network":
        why = torch_missing()
        if why:
            raise BokehInputError(why)
        return CorrectionChoice("network", "chosen in the panel", correction_model_path(lens_id, given_model))
    given = correction_model_path(lens_id, given_model) if given_model else None
    chosen, reason = core("pipeline").choose_correction(lens_id, pixel_pitch_mm, "auto", given,
                                                        labels=CORRECTION_LABELS)
    if ENGINE_METHODS[chosen] == "network":
        if torch_missing():
            return CorrectionChoice("deconvolution", f"{reason}; but this Python has no PyTorch for it")
        return CorrectionChoice("network", reason, given or correction_model_path(lens_id))
    return CorrectionChoice("deconvolution", reason)


def run_correction(image, depth_m, lens, choice: CorrectionChoice, *, geometry, sensor_noise: bool = False,
                   progress=None, cancelled=None):
    """Correct a simulated capture (H, W, 3) linear of ``lens`` with its
    depth on the sensor (H, W) metres and its ``geometry`` (what
    :func:`run_simulation` returns) by ``choice``. Returns (image, info:
    method, reason, seconds, notes, and the method's own details)."""
    if choice.method == "deconvolution":
        out, info = run_deconvolution(image, depth_m, lens, geometry, sensor_noise=sensor_noise, progress=progress,
                                      cancelled=cancelled)
    else:
        out, info = run_network(image, depth_m, lens, choice.model_path, geometry=geometry, progress=progress,
                                cancelled=cancelled)
    return out, dict(info, method=choice.method, reason=choice.reason)


def run_deconvolution(image, depth_m, lens, geometry, *, sensor_noise: bool = False, progress=None, cancelled=None):
    """``dcdi_core.correct.deconvolve`` (numpy only: no torch) of a
    simulated capture with the simulation's PSF source (the shipped OLF
    where it covers the lens, else traced and cached) and its geometry; the
    prior's weight from the sensor's noise model when Sensor Noise made the
    capture, else from the noise estimated on it. ``progress`` / ``cancelled``
    as :func:`run_bokeh`. Returns (image, info)."""
    correct = core("correct")
    report = _psf_progress(progress, cancelled)
    src = core("models.runtime.library").psf_source(lens, pixel_pitch_mm=geometry.pixel_pitch_mm,
                                                     labels=CORRECTION_LABELS)
    lib = src.library or core("render.simulate").open_library(lens, geometry, fit_depth_m=depth_m, progress=report)
    _check_cancel(cancelled)
    noise = correct.NoiseModel.sensor(SENSOR_FULL_WELL_E, SENSOR_READ_NOISE_E) if sensor_noise else None

    def windows(done, total):
        _check_cancel(cancelled)
        if progress is not None:
            progress("deconvolving", done / max(total, 1))

    res = correct.deconvolve(image, depth_m, lens, correct.DeconvOptions(noise=noise), geometry=geometry,
                             library=lib, progress=windows)
    info = dict(res.info, notes=[], seconds=res.info["seconds"]["total"], psf_source=src.kind,
                psf_source_message=src.message,
                noise_model="the sensor's (Sensor Noise)" if sensor_noise else "estimated from the image")
    return res.image, info


def run_network(image, depth_m, lens, model_path: Path, *, geometry, progress=None, cancelled=None):
    """The DACN of ``model_path`` on a simulated capture of ``lens`` with its
    depth on the sensor and its ``geometry``, as `dcdi correct --method dacn`
    runs it: ``pipeline.NetworkCorrection`` (tiled, on the capture clipped to
    [0, 1]) by ``pipeline.recover``. A refining network reads the capture's
    deconvolution too (``pipeline.Deconvolution`` of the lens at that
    geometry, with the options its training pairs and the CLI use: the noise
    estimated from the image, Sensor Noise or not), a conditioned one the
    field of each pixel, one trained told a single depth is told it again
    (``models.dacn.unaware``). ``progress`` / ``cancelled`` as
    :func:`run_bokeh` (cancel between tiles). Returns (image, info: the
    model, the lens it was trained for, notes (another lens, another pixel
    pitch), seconds, the deconvolution's PSF source where it ran)."""
    pipeline = core("pipeline")
    _check_cancel(cancelled)
    if progress is not None:
        progress("loading the network", 0.0)
    model, minfo = load_dacn_cached(model_path)
    _check_cancel(cancelled)
    if progress is not None:
        progress("correcting", 0.0)

    def tiles(done, total):
        _check_cancel(cancelled)
        if progress is not None:
            progress("correcting", done / max(total, 1))

    deconvolution = pipeline.Deconvolution(lens, geometry=geometry, labels=CORRECTION_LABELS)
    net = pipeline.NetworkCorrection(model, minfo, deconvolution=deconvolution, geometry=geometry,
                                     labels=CORRECTION_LABELS)
    notes, seconds, record = [], {}, {}
    out, _, _ = pipeline.recover(image, camera_pitch_mm=geometry.pixel_pitch_mm, depth_m=depth_m, correction=net,
                                 seconds=seconds, notes=notes, record=record, progress=tiles)
    trained_for = pipeline.trained_lens(minfo)
    if trained_for and trained_for != lens.id:
        notes.append(f"the network was trained for lens {trained_for!r}, the simulation is of {lens.id!r}")
    info = {"model": str(model_path), "trained_for": trained_for, "notes": notes,
            "seconds": seconds.get("correction", 0.0)}
    dec = record.get("deconvolution")
    if dec is not None:                          # a refining network: the deconvolution it refined
        info.update(deconvolution=dec, psf_source=dec["psf_source"],
                    psf_source_message=f"the deconvolution it refined: {dec['psf_message']}")
    return out.astype(np.float32), info


def correction_line(info: dict, seconds: float) -> str:
    """What the panel and the report say about a finished Correct:
    '<Method> (<why>), <time>' (and the network's file)."""
    used = f" with {Path(info['model']).name}" if info.get("model") else ""
    return f"{METHOD_NAMES[info['method']]}{used} ({info['reason']}), {seconds:.1f} s"


def correction_report(info: dict, seconds: float, shape) -> str:
    """The info message of a finished Correct on an image of ``shape`` (H, W, ...):
    'Correct Simulation: <correction_line>; W x H px', then the notes and the PSF source."""
    h, w = shape[:2]
    notes = "".join(f"; {n}" for n in info["notes"])
    source = f"; {info['psf_source_message']}" if info.get("psf_source_message") else ""
    return f"Correct Simulation: {correction_line(info, seconds)}; {w} x {h} px{notes}{source}"
