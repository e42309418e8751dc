"""The add-on's logic without bpy: the lens catalogue and readout, preview
size, the kept range, and the translation of the panel's settings into the
engine's jobs (``dcdi_core.app``: the bokeh, the simulation, its correction)
and of their results back (images, the panel's lines). The jobs' decisions
(which PSFs, which correction) are the engine's, the same as `dcdi`'s; the
caches between jobs (lens files and folders, readouts, PSF sources, the
loaded network) are the add-on's, held by its session (``session.SESSION``).

Units: depths and distances in metres (from the lens's first vertex, the
front of the lens on its axis, unless said otherwise), lens lengths in mm,
angles in degrees.
"""
from __future__ import annotations

import importlib.util
import math
import os
import re
import sys
import tomllib
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dcdi_core import app                  # the engine, through its application layer alone
from dcdi_core.optics import report       # the lens report: the figures the panel shows

from .session import SESSION

Cancelled = app.Cancelled        # the user pressed Esc while a job ran
DcdiError, in_words, lens_dirs = app.DcdiError, app.in_words, app.lenses.lens_dirs


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


# the engine's request fields by the names the panel shows (errors.field): what an error names
PANEL_WORDS = {"patch": "Patch Size", "interpolation": "Interpolation", "seed": "Seed", "noise": "Sensor Noise",
               "wavelength_nm": "Wavelength", "image_pixel_pitch_mm": "pixel pitch", "sensor_size": "sensor size",
               "axis_px": "optical axis", "pixel_pitch_mm": "pixel pitch", "fixed_depth_m": "fixed depth",
               "pinhole_focal_length_mm": "the camera's Focal Length",
               "perturb_fraction": "perturbation", "method": "Method", "model": "Correction Model", "lens": "Lens",
               "keep": "Kept Sharp", "focus_m": "Focus Distance", "image": "the render", "capture": "the simulation",
               "depth_m": "the depth pass", "psf_source": "PSF source", "basis": "PSF basis file",
               "olf": "Omni-Lens-Field file", "deconv": "the deconvolution's settings",
               "focus_distance_m": "Focus Distance", "fraction": "perturbation"}


def message(e: Exception) -> str:
    """An error's message in the panel's words (the engine names its request's fields)."""
    return e.in_words(PANEL_WORDS) if isinstance(e, DcdiError) else str(e)


def _note(line: str) -> str:
    return in_words(line, PANEL_WORDS)


def lens_catalogue(extra_dirs=()) -> list[LensEntry]:
    """Every ``*.toml`` in dcdi_core's lens folders ($DCDI_LENS_PATH, the
    bundled ``lenses/``) and in ``extra_dirs`` (the add-on's imported lenses);
    the first file of an id wins. A file whose name cannot be read is still
    listed (its error shows when it is chosen)."""
    entries = [LensEntry(lens_id, _lens_name(Path(path)), path, lens_number(lens_id))
               for lens_id, path in _lens_files(extra_dirs)]
    return sorted(entries, key=lambda e: _lens_order(Path(e.path)))


MAKER_LIMIT = 40          # characters: a longer ``maker`` is not a maker's name (ignored)


def _lens_order(p: Path) -> tuple:
    """Where a lens stands in the list: the lenses of a maker first, by maker
    and focal length (the file's stated one); then the designs and research
    lenses (no maker: the paper's, textbook examples, imported files), by
    focal length; then by name."""
    maker, focal = _lens_facts(p)
    return (0 if maker else 1, maker.lower(), focal, _lens_name(p).lower())


def _lens_facts(p: Path) -> tuple[str, float]:
    """(the file's ``maker``, or ''; its stated focal length in mm, or inf), read once per modification."""
    facts = SESSION.lens_names
    key = ("facts", str(p), p.stat().st_mtime_ns)
    if key not in facts:
        try:
            with open(p, "rb") as f:
                d = tomllib.load(f)
        except (OSError, tomllib.TOMLDecodeError):
            d = {}
        maker = d.get("maker")
        maker = maker.strip() if isinstance(maker, str) and len(maker.strip()) <= MAKER_LIMIT else ""
        stated = d.get("stated") if isinstance(d.get("stated"), dict) else {}
        focal = stated.get("effective_focal_length_mm")
        ok = isinstance(focal, (int, float)) and not isinstance(focal, bool) and math.isfinite(focal) and focal > 0
        facts[key] = (maker, float(focal) if ok else math.inf)
    return facts[key]


def lens_file(lens_id: str, extra_dirs=()) -> str | None:
    """The file of the lens ``lens_id`` in :func:`lens_catalogue`'s folders, or None."""
    return next((path for i, path in _lens_files(extra_dirs) if i == lens_id), None)


def _lens_files(extra_dirs) -> tuple:
    """(id, path) of the catalogue's files, listed again only when a folder changed (the session keeps them)."""
    dirs = list(lens_dirs()) + [Path(d) for d in extra_dirs if d and Path(d).is_dir()]
    return SESSION.lens_folders.get(dirs, _list_lens_files)


def _list_lens_files(dirs) -> list[tuple[str, str]]:
    seen, out = set(), []
    for d in dirs:
        for p in sorted(Path(d).glob("*.toml")):
            if p.stem in seen:
                continue
            seen.add(p.stem)
            out.append((p.stem, str(p)))
    return out


def lens_number(lens_id: str) -> int:
    """The enum number of a lens id: crc32, so it does not change when lenses are added."""
    return zlib.crc32(lens_id.encode()) & 0x7FFFFFFF


def _lens_name(p: Path, limit: int = 28) -> str:
    """The lens's name as the panel lists it: the file's ``name`` without the
    figures its source states (``F/1.8``, ``f = 26.44 mm``: the panel shows
    the traced ones, :func:`lens_readout`); where that is longer than
    ``limit`` characters, shortened by whole parts, as far as needed: the
    words an acronym of the name spells out ("MOS-S1 minimalist optical
    system" -> "MOS-S1"), then a remark in brackets to its first part
    ("(H-K9L singlet, stop in front)" -> "(H-K9L singlet)"), then the
    remark. Never cut mid-word; the whole name is the list's tooltip. The
    file's id where it has no name. A file that names its ``maker`` is
    listed under the maker's name first ("Zeiss Sonnar 50mm f/1.5"), as the
    maker sells it, unless its name starts with it."""
    names = SESSION.lens_names
    key = (str(p), p.stat().st_mtime_ns)
    if key not in names:
        try:
            with open(p, "rb") as f:
                name = str(tomllib.load(f).get("name") or "").strip()
        except (OSError, tomllib.TOMLDecodeError):
            name = None
        if name is None:
            names[key] = f"{p.stem} (unreadable file)"
            return names[key]
        maker = _lens_facts(p)[0]
        if maker and name and not name.lower().startswith(maker.lower()):
            name = f"{maker} {name}"            # as the maker sells it

        def tidy(text):
            return re.sub(r"\s+", " ", text).replace("( ", "(").replace(" )", ")").strip(" ,;:-")

        # the source's stated figures: "F/1.8", "f = 26.44 mm" (with the comma or space before them)
        short = tidy(re.sub(r"[,;]?\s*\b(?:F\s*/\s*\d+(?:\.\d+)?|f\s*=\s*\d+(?:\.\d+)?\s*mm)\b", "", name))
        if len(short) > limit:                      # an acronym's words spelled out after it
            for acronym in re.findall(r"\b([A-Z]{2,})(?=[-\s]|$)", short):
                words = r"\s+".join(rf"{c}[\w-]*" for c in acronym)
                short = tidy(re.sub(rf"(?<=\S)\s+{words}\b", "", short, count=1, flags=re.IGNORECASE))
        if len(short) > limit:                      # a remark in brackets: its first part
            short = tidy(re.sub(r"\(([^(),]*),[^()]*\)", r"(\1)", short))
        if len(short) > limit:                      # the remark
            short = tidy(re.sub(r"\s*\([^()]*\)", "", short)) or short
        names[key] = short or p.stem
    return names[key]


def load_lens_cached(path: str):
    """The Lens of a TOML file, cached by path and modification time; raises
    dcdi_core's LensFileError (naming file, surface and field) for a broken file."""
    lenses = SESSION.lenses
    key = (path, os.stat(path).st_mtime_ns)
    if key not in lenses:
        lenses[key] = app.lenses.read_lens(path)
    return lenses[key]


def lens_readout(path: str) -> dict:
    """What the panel says of a lens: ``title`` (its name as the list shows
    it, :func:`_lens_name`), ``name`` (the file's whole name), ``stated``
    (the figures its source states: a dict, possibly empty), and the traced
    figures: focal length (paraxial EFL, mm), F-number (paraxial), diagonal
    field of view (real chief ray at field 1, degrees), entrance pupil
    position (mm behind the front of the lens: its first surface on the
    axis) and sensor semi-diagonal (mm). The panel shows the traced
    figures only; a source's figures can differ (the 6P's table states
    F/1.8 for a prescription that traces to F/1.64). Cached by file and
    modification time (the real-ray field angle costs ~0.1 s)."""
    readouts = SESSION.readouts
    key = (path, os.stat(path).st_mtime_ns)
    if key not in readouts:
        lens = load_lens_cached(path)
        info = report.lens_info(lens, real_rays="field")          # `dcdi lens info`'s figures
        readouts[key] = {
            "id": lens.id, "name": lens.name, "title": _lens_name(Path(path)),
            "stated": dict(info["stated"] or {}),
            "focal_length_mm": float(info["effective_focal_length_mm"]),
            "f_number": float(info["f_number"]),
            "field_of_view_deg": info["field_of_view_deg"] or None,
            "entrance_pupil_mm": float(info["entrance_pupil_position_mm"]),
            "sensor_semi_diagonal_mm": float(info["sensor_semi_diagonal_mm"]),
        }
    return readouts[key]


# the lens list's thumbnails: the engine draws them (``app.lenses.psf_thumbnail``: PSFs at
# THUMBNAIL_FIELDS down and THUMBNAIL_DEPTHS_M across, the lens as prescribed)
THUMBNAIL_FIELDS, THUMBNAIL_DEPTHS_M = app.lenses.THUMBNAIL_FIELDS, app.lenses.THUMBNAIL_DEPTHS_M
THUMBNAIL_TILE_PX, THUMBNAIL_RAYS_PER_PX = app.lenses.THUMBNAIL_TILE_PX, app.lenses.THUMBNAIL_RAYS_PER_PX
psf_thumbnail, thumbnail_ball = app.lenses.psf_thumbnail, app.lenses.thumbnail_ball


def import_zemax(zmx_path: str, out_dir: str) -> str:
    """Convert a Zemax .zmx file to a lens TOML in ``out_dir`` (``app.lenses.import_zemax``); the TOML's path."""
    return app.lenses.import_zemax(zmx_path, out_dir)


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


def camera_aperture(lens, f_stop: float, blades: int, rotation_rad: float):
    """(``lens`` stopped down to a camera's ``f_stop`` with its iris's
    ``blades`` (Blender's: 0 round, 3 or more a polygon) turned by
    ``rotation_rad``; a note, or ''): ``app.lenses.camera_stop``."""
    return app.lenses.camera_stop(lens, f_stop, blades, rotation_rad)


def keep_range(focus_m: float, front_m: float, behind_m: float) -> tuple[float, float]:
    """The depths kept sharp, metres: [focus - front, focus + behind] (near end at least 1 mm)."""
    if not (focus_m > 0 and math.isfinite(focus_m)):
        raise BokehInputError(f"focus distance {focus_m:.4g} m: it must be positive and finite "
                              "(is the focus object behind the camera?)")
    if front_m < 0 or behind_m < 0:
        raise BokehInputError(f"kept range in front {front_m} m / behind {behind_m} m: both must be >= 0")
    return max(focus_m - front_m, 1e-3), focus_m + behind_m


def _control(progress, cancelled) -> app.Control:
    """The engine's job control of the UI's ``progress(stage, fraction)`` and ``cancelled()``."""
    def report(stage, done, total):
        if progress is not None:
            progress(stage, done / max(total, 1))
    return app.Control(progress=report, cancelled=cancelled)


# The viewport preview's PSFs where they must be traced (no shipped basis or
# OLF holds the request, e.g. a minimalist lens refocused): the engine's
# preview trace; Apply Lens Bokeh and renders trace in full.
PREVIEW_TRACE = app.PREVIEW_TRACE

# The PSF sources of the last few requests (lens file, pixel pitch, focus)
# are the session's (``SESSION.sources``): a basis or Omni-Lens-Field library
# keeps the bins it computed, so the frames of an animation with one focus, or
# a preview refreshed after a change elsewhere, pay the PSFs once. Traced
# libraries live in the disk cache.
def clear_psf_sources() -> None:
    """Drop the kept PSF sources (the next job chooses and builds its own)."""
    SESSION.sources.clear()


# The PSFs the add-on's bokeh samples (``dcdi_core.psf.sampling``; error and
# time in docs/addon.md): fields at most FIELD_STEP_PX image pixels apart (a
# 480 x 270 preview needs 19 of the 64 a 1920 x 1080 frame gets), and the
# focus rounded by at most FOCUS_TOLERANCE_PX pixels of blur diameter, so
# that a focus pull's nearby distances and an animation's frames share PSFs.
FIELD_STEP_PX = 16.0
FOCUS_TOLERANCE_PX = 0.25


def panel_words() -> "app.SourceWords":
    """How the engine's PSF messages name files and lenses in the panel: no
    file's path (the engine's own files are "the PSF basis / ray map /
    Omni-Lens-Field that ships with the add-on", another file goes by its
    name), the chosen lens "this lens", other lenses (those an OLF learned)
    by their names in the list. Listed here, not through the session's
    folder listing (a worker thread runs this)."""
    names = tuple((lens_id, _lens_name(Path(path))) for lens_id, path in _list_lens_files(list(lens_dirs())))
    return app.SourceWords(lens="this lens", shipped="that ships with the add-on", file_names=True, names=names)


def _source_info(source) -> dict:
    """The PSF source's kind, quality and message (made in the panel's words, :func:`panel_words`)."""
    return {"psf_source": source.kind, "psf_source_message": _note(source.message), "psf_quality": source.quality}


# where a job's blur came from, in an artist's words (the engine's message is the status line's tooltip)
SOURCE_WORDS = {"raymap": "the lens's ray map", "trace": "rays traced through the lens",
                "basis": "the lens's PSF basis", "olf": "the OLF"}


def source_words(info: dict) -> str:
    """One short line on a job's blur from its data (the source's kind, the
    error budget's plan): "Blur from the lens's ray map, about 41 dB"."""
    words = f"Blur from {SOURCE_WORDS.get(info.get('psf_source'), 'the lens')}"
    q = info.get("quality") or {}
    if q.get("expected_db") is not None:
        words += f", about {q['expected_db']:.0f} dB"
    return words


def run_bokeh(image, depth, lens, *, focus_m: float, keep: tuple[float, float], patch: int = 16,
              refocus: bool = True, progress=None, cancelled=None, preview: bool = False,
              max_error_db: float | None = None, lens_geometry: bool = False,
              pinhole_focal_length_mm: float | None = None):
    """The lens's depth of field on an all-in-focus (H, W, 3) float32 linear
    image with depth (H, W) metres: ``dcdi_core.app.bokeh`` (`dcdi bokeh
    --focus F --keep NEAR FAR`), the lens focused at ``focus_m`` (or, with
    ``refocus`` False, as its prescription stands), depths in ``keep``
    exactly sharp. ``progress(stage, fraction)`` is called while PSFs are
    built and layers convolved; ``cancelled()`` returning True stops the job
    with :class:`Cancelled`. ``preview``: PSFs that must be traced are traced
    with ``PREVIEW_TRACE`` (info's ``psf_quality`` 'preview') where the
    lens has no error table. ``max_error_db``: the error budget (dB; None:
    the preview's or the render's default, ``app.DEFAULT_BUDGET_DB``),
    the plan in info's ``quality``. ``lens_geometry``: the picture moved
    as the lens at its focus moves it (breathing, distortion; `dcdi bokeh
    --distort`), the render read as a pinhole's of
    ``pinhole_focal_length_mm`` (:func:`reading.pinhole_focal_length_mm`;
    None: the lens's own). Returns
    (image, info: the bokeh's, the PSF source and its message, and
    ``focus_note`` where nothing in view lies in the kept range)."""
    # the PSF work planned by the job's error budget (``psf.budget``); FIELD_STEP_PX and the preview's
    # lighter trace where a lens has no error table
    psf = app.PSFRequest(preview=preview, field_step_px=FIELD_STEP_PX, focus_tolerance_px=FOCUS_TOLERANCE_PX,
                         max_error_db=app.DEFAULT_BUDGET_DB["preview" if preview else "render"]
                         if max_error_db is None else float(max_error_db), words=panel_words())
    render = app.RenderRequest(lens, patch=patch, pinhole_focal_length_mm=pinhole_focal_length_mm if lens_geometry else None)
    request = app.BokehRequest(image, depth, lens, keep=tuple(keep), focus_m=float(focus_m) if refocus else None,
                               render=render, psf=psf, image_name="the render", distortion=bool(lens_geometry))
    r = app.bokeh(request, _control(progress, cancelled), cache=SESSION.sources)
    info = dict(r.info, focus_m=float(focus_m), keep_m=[float(keep[0]), float(keep[1])], refocus=bool(refocus),
                seconds=dict(r.seconds),
                pixel_pitch_mm=float(r.geometry.pixel_pitch_mm), focus_note="; ".join(_note(n) for n in r.notes),
                **_source_info(r.source))
    q = r.info.get("quality")
    if q and q.get("expected_db") is not None:      # the error budget's plan (psf.budget), in the panel's words
        info["psf_source_message"] += (f"; PSFs planned for {q['budget_db']:g} dB: about {q['expected_db']:.0f} dB "
                                       "from converged ones")
    if "focus_used_m" in r.info:            # the PSFs of a nearby focus serve this one (FOCUS_TOLERANCE_PX)
        info["psf_source_message"] += (f"; its PSFs at {r.info['focus_used_m']:.3g} m serve the focus at "
                                       f"{float(focus_m):.3g} m (blurs within {FOCUS_TOLERANCE_PX:g} px)")
    return r.image, info


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
    conversion); Lens Geometry (the depth of field's) and the camera's
    pinhole focal length on the lens's sensor (None: the lens's own)."""

    effect: str
    focus_m: float
    keep: tuple[float, float]
    refocus: bool
    entrance_pupil_mm: float
    metres_per_unit: float = 1.0
    lens_geometry: bool = False
    pinhole_focal_length_mm: float | None = None

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
    depth = app.camera.depth_from_planar_z(z, request.entrance_pupil_mm, request.metres_per_unit)
    rgb = np.nan_to_num(np.asarray(rgb, np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    if request.effect == "dof":
        out, info = run_bokeh(rgb, depth, lens, focus_m=request.focus_m, keep=request.keep,
                              refocus=request.refocus, progress=progress, cancelled=cancelled,
                              lens_geometry=request.lens_geometry,
                              pinhole_focal_length_mm=request.pinhole_focal_length_mm)
    else:
        out, _, _, info = run_simulation(rgb, depth, lens, focus_m=request.focus_m, progress=progress,
                                         cancelled=cancelled, pinhole_focal_length_mm=request.pinhole_focal_length_mm)
    return out, depth, dict(info, effect=request.effect)


# ------------------------------------------------------------------ the DCDI round trip
def run_simulation(image, depth, lens, *, noise: bool = False, seed: int = 0, focus_m: float | None = None,
                   progress=None, cancelled=None, pinhole_focal_length_mm: float | None = None):
    """The all-in-focus (H, W, 3) render with depth (H, W) metres as ``lens``
    (as prescribed, or with ``focus_m`` its sensor moved to focus there)
    would have taken it: ``dcdi_core.app.simulate`` (`dcdi simulate
    [--focus F] [--noise --seed S]`: distortion, then patch-wise PSFs of
    field and depth; sensor noise if ``noise``, seeded by ``seed``).
    ``progress`` / ``cancelled`` as :func:`run_bokeh`; the render read as a
    pinhole's of ``pinhole_focal_length_mm`` (None: the lens's own). Returns (image, depth
    on the sensor (NaN where the lens images nothing), the image's geometry
    on the sensor, info with ``record``: what the capture remembers, the
    defaults of its correction)."""
    psf = replace(app.PSFSettings(), focus_distance_m=None if focus_m is None else float(focus_m))
    render = app.RenderRequest(lens, psf=psf, noise=bool(noise), seed=int(seed) if noise else None,
                           pinhole_focal_length_mm=pinhole_focal_length_mm)
    r = app.simulate(app.SimulateRequest(image, depth, lens, render, image_name="the render",
                                         psf=app.PSFRequest(max_error_db=app.DEFAULT_BUDGET_DB["render"],
                                                                 words=panel_words())),
                     _control(progress, cancelled), cache=SESSION.sources)
    info = dict(r.info, lens=lens.id, pixel_pitch_mm=float(r.geometry.pixel_pitch_mm), record=r.record,
                **_source_info(r.source))
    return r.image, r.depth_m.astype(np.float32), r.geometry, info


def torch_install_command(python: str | None = None) -> str:
    """The command that installs the PyTorch the engine is tested with into ``python`` (default: this one)."""
    return f'"{python or sys.executable}" -m pip install torch=={app.TORCH_VERSION}'


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


def correction_model_path(lens_id: str, given: str = "") -> Path | None:
    """The Correction Model file (an absolute path, an exported .npz or a run
    folder), or None for the lens's shipped network (the engine finds it)."""
    if not given:
        return None
    p = Path(given)
    if not p.exists():
        raise BokehInputError(f"correction model {str(p)!r}: no such file (give a DACN exported with "
                              "`dcdi dacn export` (.npz), or leave it empty for the lens's shipped one)")
    return p


def load_dacn_cached(path, weights: str = "ema", device: str = "cpu"):
    """(model, info) of ``models.dacn.correct.load_dacn``, the last one kept
    (by path and modification time); a missing torch is reported with the
    install command."""
    key = (str(path), os.stat(path).st_mtime_ns, weights, device)
    networks = SESSION.networks
    if key not in networks:
        networks.clear()                     # one network at a time: they are the biggest thing held
        try:
            networks[key] = app.load_dacn(path, weights=weights, device=device)
        except app.TorchMissingError:
            raise BokehInputError(_torch_message()) from None
        except ImportError as e:             # a torch that is there but does not import
            raise BokehInputError(_torch_message(f" that imports ({e})")) from None
    return networks[key]


# ------------------------------------------------------------------ Correct Simulation
# the panel's Correction Method, and the engine's name of each (app.CorrectRequest's method)
METHODS = ("auto", "deconvolution", "network")
METHOD_NAMES = {"auto": "Auto", "deconvolution": "Deconvolution", "network": "Network"}
ENGINE_METHODS = {"auto": "auto", "deconvolution": "deconv", "network": "dacn"}
PANEL_METHODS = {"deconv": "deconvolution", "dacn": "network"}


@dataclass(frozen=True)
class CorrectionChoice:
    """What Correct runs: ``method`` ('deconvolution' or 'network'), why
    (``reason``, for the panel and the report), and the network's file
    (None: the lens's shipped one)."""

    method: str
    reason: str
    model_path: Path | None = None


def _correct_request(image, depth_m, lens, method: str, model_path, record=None,
                     geometry=None) -> "app.CorrectRequest":
    """The engine's request: the capture on the lens's sensor from its record, or from ``geometry``."""
    render = None
    if geometry is not None and record is None and isinstance(lens, app.lenses.Lens):
        render = app.RenderRequest(lens, image_pixel_pitch_mm=float(geometry.pixel_pitch_mm),
                               axis_px=tuple(geometry.center_px))
    return app.CorrectRequest(image, depth_m, lens, ENGINE_METHODS[method], model_path, render=render,
                              recorded=record, image_name="the simulation",
                              psf=app.PSFRequest(words=panel_words()))


def choose_correction(requested: str, lens_id: str, pixel_pitch_mm: float, given_model: str = "", *,
                      lens=None, record=None) -> CorrectionChoice:
    """The method for ``requested`` ('auto', 'deconvolution' or 'network')
    on a simulation of ``lens`` at ``pixel_pitch_mm`` (mm per pixel on the
    sensor), with the panel's Correction Model file ``given_model`` (''
    for the lens's shipped network): the engine's rule
    (``app.correction.choose``, `dcdi correct --method`'s). Network needs
    torch (the message says what to install); Auto falls back to the
    deconvolution where no torch imports."""
    if requested not in METHODS:
        raise BokehInputError(f"correction method {requested!r}: allowed {', '.join(METHODS)}")
    if requested == "network":
        why = torch_missing()
        if why:
            raise BokehInputError(why)
    # the deconvolution reads no network file: a Correction Model left set is not used
    model = correction_model_path(lens_id, given_model) if requested != "deconvolution" else None
    try:
        chosen, reason = app.choose_correction(_correct_request(None, None, lens if lens is not None else _LensId(lens_id),
                                                 requested, model, record), pixel_pitch_mm)
    except DcdiError as e:                   # what cannot run, said in the panel's words
        raise BokehInputError(message(e)) from None
    if requested != "auto":
        reason = "chosen in the panel"
    if chosen != "dacn":                     # a network Auto passed over (no torch) is not run
        return CorrectionChoice(PANEL_METHODS[chosen], _note(reason))
    return CorrectionChoice(PANEL_METHODS[chosen], _note(reason), model or app.shipped_model("dacn", lens_id))


@dataclass(frozen=True)
class _LensId:
    """A lens known by its id alone (the rule reads only the id)."""

    id: str


def run_correction(image, depth_m, lens, choice: CorrectionChoice, *, geometry=None, sensor_noise: bool = False,
                   record=None, progress=None, cancelled=None):
    """Correct a simulated capture (H, W, 3) linear of ``lens`` with its
    depth on the sensor (H, W) metres by ``choice``: ``dcdi_core.app.correct``
    (`dcdi correct --method deconv|dacn` on the capture file :func:`run_simulation`
    would write), the capture's geometry and noise model from its ``record``
    (what :func:`run_simulation` returns in its info), else its ``geometry``
    on the sensor (None: it spans the sensor's diagonal). Returns (image, info:
    method, reason, seconds, notes, and the method's own details)."""
    request = _correct_request(image, depth_m, lens, choice.method, choice.model_path, record, geometry)
    r = app.correct(request, _control(progress, cancelled), networks=load_dacn_cached)
    # the reason is the choice's (Auto's rule, made when Correct was asked for), not "asked for"
    info = dict(r.info, method=PANEL_METHODS[r.method], reason=choice.reason, notes=[_note(n) for n in r.notes],
                seconds=r.seconds["correction"])
    if r.method == "dacn":
        info["model"] = str(r.info.get("model") or choice.model_path or "")
    if "psf_message" in r.info:
        info["psf_source_message"] = _note(r.info["psf_message"])
    if r.method == "deconv":
        info["noise_model"] = ("the sensor's (Sensor Noise)" if record is not None and record.noise
                               else "estimated from the image")
    return r.image, info


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
