"""PSF sources for the renderer besides tracing: the PSF basis and the Omni-Lens-Field (numpy only).

``render.psfmap.psf_map`` reads a PSF library's interface (``grid``,
``fields``, ``kernel_size``, ``depth_bins``, ``field_weights``,
``bins_needed``, ``ensure``, ``psf``, ``computed``; ``pixel_pitch_mm`` and
``settings`` for the simulator's checks). :class:`OLFLibrary` is a
``PSFLibrary`` whose bins are filled by the OLF's forward pass instead of
ray tracing, at the same grid, so the renderer needs no change and never
imports ``models`` (docs/design.md: the caller hands it a PSF source).

:func:`psf_source` decides which source serves a request by the source
rule (``psf.rule``: the stores in ``RULE_ORDER``, else tracing); either way
it says which and why in one line. The OLF covers a request where the lens's
optical fingerprint is the learned one, the PSF settings, spectral response
and focus are those it learned, the pixel pitch is the learned one or
coarser and the grid lies within its ranges. The chosen :class:`PSFSource`
opens its PSFs at a job's geometry (:meth:`PSFSource.at`); a library makes
its own at another pitch (``PSFLibrary.at_geometry``: a ray map's from its
ray map). The CLI and the Blender add-on both choose through it.

At a pixel pitch coarser than the learned one, the network's kernels (pixel
histograms at the learned pitch) are area-resampled exactly
(``psf.pitch.area_resample``); a finer pitch is traced, never upsampled.
"""
from __future__ import annotations

import time
import dataclasses
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np

import math
import warnings

from ..control import Control
from ..errors import InputRangeError, LensMismatchError, ModelError, field
from ..io.npzfile import FileCache
from ..optics.errors import OpticsError
from .basis import BasisLibrary, open_store, shipped_store
from .compute import KernelTooSmallWarning, PSFSettings
from .library import MAX_FITTED_KERNEL, LibraryGrid, PSFLibrary, _fitted, open_library, valid_depth_mask  # noqa: F401 (served from here)
from .sampling import field_grid
from .pitch import SAME_GIVEN_RTOL, area_resample, check_downsampling, resampled_size, same_pitch
from ..shipped import NETWORKS, WEIGHTS_DIR, for_lens, is_shipped_file, olf_rays_file
from .olf import OmniLensField, load_olf_file
from .raymap import RayMap, RayMapLibrary, open_raymap
from .rayfield import RayFieldOLF
from .rule import RULE_ORDER, rule_text

SHIPPED = WEIGHTS_DIR / "olf-radial.npz"
SOURCES = ("basis", "raymap", "olf", "trace")
# each source in a message's words
SOURCE_NAMES = {"basis": "PSF basis", "raymap": "ray map", "olf": "Omni-Lens-Field"}
SHORT_NAMES = {"basis": "basis", "raymap": "ray map", "olf": "OLF"}


@dataclass(frozen=True)
class SourceWords:
    """How a PSF source's message names the files it read and the lenses.
    The defaults (the command line's) name a file by its path and a lens by
    its id. A front end may name the request's own lens in its words
    (``lens``: "this lens"), the engine's own files by what they are
    (``shipped``: "that ships with the add-on": "the ray map that ships
    with the add-on"), any other file by its name alone (``file_names``)
    and other lenses by their names (``names``: (id, name) pairs). The
    engine makes its message in these words; no front end rewrites it."""

    lens: str | None = None
    shipped: str | None = None
    file_names: bool = False
    names: tuple = ()

    def _ships(self, path) -> bool:
        return self.shipped is not None and is_shipped_file(path)

    def store(self, kind: str, path) -> str:
        """A store named with what it is: "the ray map /…/6p.npz"."""
        return f"the {kind} {self.shipped}" if self._ships(path) else f"the {kind} {self.file(kind, path)}"

    def file(self, kind: str, path) -> str:
        """A store's file where the sentence names it alone: "/…/6p.npz", "the shipped ray map"."""
        if self._ships(path):
            return f"the shipped {kind}"
        return Path(path).name if self.file_names else str(path)

    def name(self, lens_id: str) -> str:
        """Another lens than the request's (one an OLF learned): by its name."""
        return dict(self.names).get(lens_id, lens_id)

    def lens_of(self, lens, *, file: bool = False) -> str:
        """The request's lens where the sentence is about it: its id (with
        ``file``, and its file's path), or the front end's words."""
        if self.lens is not None:
            return self.lens
        return f"{lens.id} ({lens.path})" if file and getattr(lens, "path", None) else f"{lens.id}"

    def quoted(self, lens) -> str:
        """'lens '6p'' or "this lens"."""
        return self.lens if self.lens is not None else f"lens {lens.id!r}"

    def lead(self, lens, sep: str = ", ") -> str:
        """'6p, ' before a source's figures, or '' where the front end's words say the lens already."""
        return "" if self.lens is not None else f"{lens.id}{sep}"


DEFAULT_WORDS = SourceWords()


def shipped_olf_files() -> list[Path]:
    """The OLF files that ship with the engine (``dcdi_core/models/weights/olf-*.npz``;
    the folder also holds the DACN and depth networks)."""
    return NETWORKS["olf"].shipped_files()


class OLFLibrary(PSFLibrary):
    """A PSF library of one lens whose bins come from an Omni-Lens-Field.

    Same grid semantics as the traced library (fields along sensor +y,
    kernel rows along the radial direction, depth bins uniform in diopters
    plus infinity, linear interpolation between them); ``ensure`` runs the
    network for the bins asked for (all fields of a bin at once) and never
    traces. ``last_network_s`` is the time of the forward passes so far."""

    def __init__(self, olf: OmniLensField, lens, grid: LibraryGrid | None = None, *,
                 pixel_pitch_mm: float | None = None, focus_m: float | None = None):
        li = olf.check_lens(lens)               # refuses another prescription
        entry = olf.lens_entry(lens.id)
        if grid is None:       # the grid of the traced library it learned from
            grid = LibraryGrid(**entry["library_grid"]) if entry.get("library_grid") else LibraryGrid()
        near, far = entry["depth_range_m"]
        if grid.near_m < near - 1e-9 or grid.far_m > far + 1e-9:
            raise InputRangeError("library grid depths", (grid.near_m, grid.far_m),
                                  f"within the OLF's trained [{near}, {far}] m ({olf.path})")
        learned = float(entry["pixel_pitch_mm"])
        pitch = learned if pixel_pitch_mm is None else float(pixel_pitch_mm)
        check_downsampling(learned, pitch, f"pixel pitch (mm; {olf.path} learned {lens.id} at {learned:.6g} mm)")
        k = resampled_size(int(entry["kernel_size"]), learned, pitch)
        s = dict(entry["psf_settings"])
        s["band_nm"] = tuple(s["band_nm"])
        settings = replace(PSFSettings(**s), kernel_size=k, focus_distance_m=focus_m, pixel_pitch_mm=pitch)
        self.olf, self.lens_index, self.focus_m = olf, li, focus_m
        self.learned_pitch_mm = learned
        self.last_network_s = 0.0
        meta = {"format": "olf", "algorithm": entry.get("psf_algorithm"), "lens_id": lens.id,
                "lens_file": str(lens.path), "lens_fingerprint": entry["fingerprint"],
                "settings": settings.as_dict(), "grid": {"n_fields": grid.n_fields, "n_depths": grid.n_depths,
                                                         "near_m": grid.near_m, "far_m": grid.far_m},
                "pixel_pitch_mm": pitch, "learned_pixel_pitch_mm": learned, "wavelengths_nm": [],
                "response": {"sha256": "olf:" + str(olf.meta.get("checksum"))}, "olf_file": olf.path}
        super().__init__(lens, settings, grid, None, meta=meta)

    @property
    def resampled(self) -> bool:
        """True when the kernels are area-resampled from the learned pitch."""
        return not same_pitch(self.pixel_pitch_mm, self.learned_pitch_mm)

    def kernels(self, field, depth_m, *, dtype=np.float32) -> np.ndarray:
        """The OLF's PSFs (..., 3, k, k) at fields x depths (broadcast), at the
        library's pixel pitch: the network's kernels at the learned pitch,
        area-resampled (``psf.pitch``) when the library's is coarser."""
        t = time.perf_counter()
        out = self.olf.psf(self.lens, field, depth_m, self.focus_m, dtype=dtype)
        self.last_network_s += time.perf_counter() - t
        if self.resampled:
            out = area_resample(out, self.learned_pitch_mm, self.pixel_pitch_mm, self.kernel_size)
        return out

    def ensure(self, depth_m=None, *, bins=None, clamp_near: bool = False, progress=None) -> list[int]:
        want = np.asarray(bins if bins is not None else self.bins_needed(depth_m, clamp_near=clamp_near), int)
        todo = [int(b) for b in want if not self.computed[b]]
        if not todo:
            return []
        kernels = self.kernels(self.fields[None, :], self.depths_m[todo][:, None])
        for j, b in enumerate(todo):
            self.psf[b] = kernels[j]
            self.computed[b] = True
        # what the traced library records beside its kernels: the OLF learned
        # kernels that hold (at least) its energy fraction, renormalised to 1
        self.energy_outside[todo] = 0.0
        self.kernel_size_needed[todo] = self.kernel_size
        if progress:
            progress(len(todo) * len(self.fields), len(todo) * len(self.fields))
        return todo

    def save(self, path) -> None:        # nothing to cache: the network is the store
        raise ModelError("an OLF-backed library is not saved; it is computed from the OLF file")


@dataclass
class PSFSource:
    """Which PSF source serves a request: ``kind`` 'basis' (a compressed
    traced library), 'raymap' (the lens's ray map), 'olf' (each with its
    library) or 'trace' (library None: the caller opens a traced one), and
    why."""

    kind: str
    message: str
    library: PSFLibrary | None = None
    olf_file: str | None = None
    basis_file: str | None = None
    raymap_file: str | None = None
    lens: object = None
    # the traced libraries this source opened, by their settings: a job that opens it twice (the depth from
    # blur, then the deconvolution) shares the bins, and a kernel grown for the second starts from the first
    opened: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def plans(self) -> bool:
        """Whether the job's error budget plans this source's PSF work
        (rays, wavelengths, field step): a trace, a ray map or an OLF in ray
        space makes its PSFs; a basis or a network serves them as stored."""
        return self.kind == "trace" or self.deposits

    @property
    def deposits(self) -> bool:
        """Whether its PSFs are deposited from rays (a ray map, an OLF in ray space)."""
        return isinstance(self.library, RayMapLibrary)

    def at(self, geometry, request: "PSFRequest", *, fit_depth_m=None,
           control: Control | None = None) -> "PSFSourceResult":
        """This source's PSFs for an image at ``geometry`` (``render.geometry.
        ImageGeometry``) as ``request`` asks (its settings as the error budget
        planned them, ``app.render.budgeted``): a basis's or an OLF's library
        as stored; a ray map's deposited, or a traced library (cached on
        disk), each kernel grown to hold the blur of ``fit_depth_m`` (a depth
        map, metres; with ``request.fit_kernel``). ``control`` reports the
        PSFs made (stage 'PSFs') and stops them when cancelled."""
        control = control or Control()
        control.say(self.message)
        if self.kind in ("basis", "olf") and not self.deposits:
            return PSFSourceResult(self.kind, self.message, self.library, self.olf_file, self.basis_file)
        settings, quality = request.settings or PSFSettings(), "full"
        if request.preview:
            settings, quality = replace(settings, **PREVIEW_TRACE), "preview"
        if request.kernel_size is not None:
            settings = replace(settings, kernel_size=request.kernel_size)
        fit = fit_depth_m if request.fit_kernel and request.kernel_size is None else None
        progress = control.counter("PSFs")
        if self.deposits:      # a ray map's (or an OLF's in ray space): the settings a trace would take
            library = self.library.at_geometry(geometry, settings, fit_depth_m=fit, progress=progress)
            return PSFSourceResult(self.kind, self.message, library, self.olf_file, quality=quality,
                                   raymap_file=self.raymap_file)
        library = open_library(self.lens, geometry, settings, _request_grid(self.lens, geometry, request),
                               response=request.response, fit_depth_m=fit, progress=progress, kept=self.opened)
        return PSFSourceResult("trace", self.message, library, self.olf_file, self.basis_file, quality)


def _settings_differences(learned: dict, settings: PSFSettings | None, *, rays_at_least: bool = False,
                          verb: str = "learned") -> list[str]:
    """What in ``settings`` differs from the PSF settings a source learned or
    stored (kernel size, pixel pitch and focus are checked apart; with
    ``rays_at_least``, more stored rays than asked serve the request: the same
    PSFs with less ray noise)."""
    if settings is None:
        return []
    asked = settings.as_dict()
    out = []
    for key, v in asked.items():
        if key in ("kernel_size", "pixel_pitch_mm", "focus_distance_m"):
            continue
        have = learned.get(key)
        if key == "pupil_samples" and rays_at_least and have is not None and have >= v:
            continue
        if isinstance(have, list):
            have = list(have)
            v = list(v)
        if have != v:
            out.append(f"{key} {v!r} (it {verb} {have!r})")
    return out


# a refocus, a new pixel pitch or another lens opens a new source, but not the
# 10 MB file again (0.1-0.3 s of every focus change in the add-on's preview);
# one file at a time: the shipped one, or the user's
_load_olf = FileCache(load_olf_file, 2, "Omni-Lens-Field files")


# the request's fields the source's messages name (errors.field: each front end shows them in its own words;
# a caller may still pass labels, a label None leaving the mention out)
PSF_SOURCE_LABELS = MappingProxyType({"psf_source": field("psf_source"), "basis": field("basis"), "olf": field("olf")})


def psf_source(lens, *, source: str | None = None, olf_file=None, pixel_pitch_mm: float | None = None,
               settings: PSFSettings | None = None, kernel_size: int | None = None, focus_m=None,
               custom_response: bool = False, grid: LibraryGrid | None = None,
               need_field: bool = True, basis_file=None, labels=None, olf_grid: LibraryGrid | None = None,
               response=None, words: SourceWords | None = None) -> PSFSource:
    """The PSF source for ``lens`` and a request: ``source`` 'basis' (the
    lens's compressed library), 'olf' (the OLF), each an error saying why if
    it cannot serve, 'trace', or None: the source rule (``psf.rule.
    rule_text``; an ``olf_file`` given without a
    ``basis_file`` goes first). ``olf_file`` / ``basis_file``: the files
    (default: the shipped ones). The request: the image's pixel pitch (None:
    the lens's sensor), the PSF settings asked for, an explicit kernel size,
    a focus distance (None: as prescribed), a custom spectral response.
    ``labels`` ({'psf_source', 'basis', 'olf'}: the CLI's options by
    request's fields by default, shown in each front end's words; a label None
    leaves the option unnamed) name the choices in the messages. ``olf_grid``:
    the grid an OLF serves on when ``grid`` is None (a basis keeps its own).
    ``response``: the custom spectral response itself, which a ray map
    serves (the others refuse any). ``words``: how the message names
    files and lenses (:class:`SourceWords`; None: by path and id)."""
    src = _psf_source(lens, source, olf_file, pixel_pitch_mm, settings, kernel_size, focus_m, custom_response, grid,
                      basis_file, labels, olf_grid, response, words or DEFAULT_WORDS)
    src.lens = lens
    return src


def _psf_source(lens, source, olf_file, pixel_pitch_mm, settings, kernel_size, focus_m, custom_response, grid,
                basis_file, labels, olf_grid, response, w: SourceWords) -> PSFSource:
    lab = {**PSF_SOURCE_LABELS, **(labels or {})}
    if source not in (None,) + SOURCES:
        raise InputRangeError("psf source", source,
                              "basis, olf, trace, or none (the first of basis and olf that covers the request)")
    if source == "trace":
        return PSFSource("trace", "PSFs traced" + (f" ({lab['psf_source']} trace)" if lab["psf_source"] else ""))
    reasons: list[str] = []
    # an OLF file given without a basis file is the source asked for: it goes first
    order = ("olf",) + tuple(k for k in RULE_ORDER if k != "olf") if olf_file and not basis_file else RULE_ORDER
    for kind in order:
        if source not in (None, kind):
            continue
        if kind == "raymap":
            src, why = _try_raymap(lens, pixel_pitch_mm, settings, kernel_size, custom_response and response is None,
                                   response, grid if grid is not None else olf_grid, w)
        elif kind == "basis":
            src, why = _try_basis(lens, basis_file, pixel_pitch_mm, settings, kernel_size, focus_m, custom_response,
                                  grid, lab[kind], w)
        else:
            src, why = _try_olf(lens, olf_file, pixel_pitch_mm, settings, kernel_size, focus_m, custom_response,
                                grid if grid is not None else olf_grid, lab[kind], w, response)
        if src is not None:
            return src
        if source == kind:
            raise ModelError(f"{lab['psf_source'] or 'PSF source'} {kind}: the {SOURCE_NAMES[kind]} cannot serve "
                             f"this request: {why}")
        reasons.append(f"{SHORT_NAMES[kind]}: {why}")
    olf_path = Path(olf_file) if olf_file else (SHIPPED if SHIPPED.exists() else None)
    return PSFSource("trace", "PSFs traced: " + "; ".join(reasons), None,
                     None if olf_path is None else str(olf_path))


def _stopped_down(lens, kind, path, w: SourceWords) -> str | None:
    """Why a store of the lens wide open does not serve it stopped down (None: it is not)."""
    if not getattr(lens, "iris", ""):
        return None
    return f"{w.lens_of(lens)} is stopped down ({lens.iris}); {w.file(kind, path)} holds it as prescribed (wide open)"


def _none_given(label: str | None) -> str:
    """' and none was given (LABEL)' where the user can give one."""
    return f" and none was given ({label})" if label else ""


def _try_basis(lens, basis_file, pitch, settings, kernel_size, focus_m, custom_response, grid, label="--basis",
               w: SourceWords = DEFAULT_WORDS):
    """(PSFSource, None) where the lens's PSF basis serves the request, else (None, why); ``label``: the
    option that gives a basis file (None: none). A refocused lens is served by a focus stack (the shipped
    one of the lens, or the file given) that covers the focus."""
    stack = focus_m is not None
    path = Path(basis_file) if basis_file else shipped_store(lens.id, focus_stack=stack)
    if path is None:
        if stack:
            return None, (f"focus {focus_m:.3g} m asked for; no focus-stack PSF basis of {w.lens_of(lens)} ships "
                          f"with this engine{_none_given(label)}")
        return None, f"no PSF basis of {w.lens_of(lens)} ships with this engine{_none_given(label)}"
    try:
        store = open_store(path)
        store.check_lens(lens)
    except OpticsError as e:
        return None, _stopped_down(lens, "PSF basis", path, w) or str(e)
    f, it = w.file("PSF basis", path), w.lens_of(lens)
    if stack and store.focus_diopters is None:
        return None, f"focus {focus_m:.3g} m asked for; {f} holds {it} at its prescribed focus"
    if stack and not store.covers_focus(focus_m):
        near, far = store.focus_range_m()
        return None, f"focus {focus_m:.3g} m is outside {f}'s {near:.3g} m to {far:.3g} m"
    if not stack and store.focus_diopters is not None:
        return None, f"{f} is a focus stack: it serves {it} refocused, not at its prescribed focus"
    stored = store.pixel_pitch_mm
    if pitch is not None and not (pitch >= stored or same_pitch(pitch, stored)):
        return None, (f"the image's pixel pitch {pitch * 1000:.6g} um is finer than the {stored * 1000:.6g} um "
                      f"{f} holds {it} at")
    k = resampled_size(store.kernel_size, stored, stored if pitch is None else pitch)
    if kernel_size is not None and kernel_size != k:
        return None, f"a {kernel_size} px kernel was asked for; {f} serves {it} at {k} px at this pitch"
    if custom_response:
        return None, "a custom spectral response was given; the PSF basis holds the shipped one"
    if grid is not None and grid != store.grid:
        return None, f"a library grid {grid} was asked for; {f} holds {store.grid}"
    diff = _settings_differences(store.meta["psf_settings"], settings, rays_at_least=True, verb="holds")
    if diff:
        return None, "PSF settings differ from the stored ones: " + "; ".join(diff)
    lib = BasisLibrary(store, lens, pixel_pitch_mm=pitch, focus_m=focus_m)
    pixels = (f"{lib.pixel_pitch_mm * 1000:.4g} um pixels, its {stored * 1000:.4g} um kernels area-resampled"
              if lib.resampled else f"{lib.pixel_pitch_mm * 1000:.4g} um pixels")
    focus = "prescribed focus"
    if stack:
        near, far = store.focus_range_m()
        focus = (f"a focus stack: focus {focus_m:.3g} m from {len(store.focus_diopters)} focus distances "
                 f"{near:.3g} m to {far:.3g} m")
    return PSFSource("basis", f"PSFs from {w.store('PSF basis', path)} ({w.lead(lens)}rank {store.rank}, {pixels}, "
                              f"{lib.kernel_size} x {lib.kernel_size} px, {focus})",
                     lib, None, str(path)), None


def _try_olf(lens, olf_file, pitch, settings, kernel_size, focus_m, custom_response, grid, label="--olf",
             w: SourceWords = DEFAULT_WORDS, response=None):
    """(PSFSource, None) where the OLF serves the request, else (None, why); ``label``: the option that gives
    an OLF file (None: none). Without a file, the shipped ones in turn: the OLF in ray space (any focus and
    stop of the lenses it holds), then the network."""
    paths = [Path(olf_file)] if olf_file else [p for p in (olf_rays_file(), SHIPPED) if p is not None and p.exists()]
    if not paths:
        return None, f"no OLF file ships with this engine{_none_given(label)}"
    reasons = []
    for path in paths:
        try:
            olf = _load_olf(path)
            if isinstance(olf, RayFieldOLF):
                src, why = _try_olf_rays(olf, lens, pitch, settings, kernel_size, focus_m, custom_response,
                                         response, grid, w)
            else:
                src, why = _try_olf_network(olf, lens, pitch, settings, kernel_size, focus_m, custom_response,
                                            grid, w)
        except (LensMismatchError, ModelError, InputRangeError) as e:
            src, why = None, str(e)
        if src is not None:
            return src, None
        reasons.append(why)
    return None, "; ".join(reasons)


def _try_olf_network(olf: OmniLensField, lens, pitch, settings, kernel_size, focus_m, custom_response, grid,
                     w: SourceWords):
    """(PSFSource, None) where the OLF network serves the request, else (None, why)."""
    reason = _why_not(olf, lens, pitch, settings, kernel_size, focus_m, custom_response, w)
    if reason is not None:
        return None, reason
    lib = OLFLibrary(olf, lens, grid, pixel_pitch_mm=pitch, focus_m=focus_m)
    k = lib.kernel_size
    pixels = (f"{lib.pixel_pitch_mm * 1000:.4g} um pixels, its {lib.learned_pitch_mm * 1000:.4g} um kernels "
              "area-resampled" if lib.resampled else f"{lib.pixel_pitch_mm * 1000:.4g} um pixels")
    return PSFSource("olf", f"PSFs from {w.store('Omni-Lens-Field', olf.path)} ({w.lead(lens, ': ')}its learned "
                            f"prescription, {pixels}, {k} x {k} px, "
                            + ("prescribed focus" if focus_m is None else f"focus {focus_m:.3g} m") + ")",
                     lib, str(olf.path)), None


def _try_olf_rays(olf: RayFieldOLF, lens, pitch, settings, kernel_size, focus_m, custom_response, response, grid,
                  w: SourceWords):
    """(PSFSource, None) where the OLF in ray space serves the request (as a
    ray map does: any focus, f-number, blades, pitch, rays and wavelengths of
    a lens it holds), else (None, why)."""
    f = w.file("Omni-Lens-Field", olf.path)
    if lens.id not in olf.lens_ids:
        return None, f"{f} did not learn {w.quoted(lens)} (it learned {', '.join(w.name(i) for i in olf.lens_ids)})"
    if custom_response and response is None:
        return None, "a custom spectral response was asked for without its curves"
    s = settings or PSFSettings()
    if s.focus_distance_m != focus_m:
        s = replace(s, focus_distance_m=focus_m)
    try:
        lib = raymap_library(olf.map_for(lens.id), lens, pitch, s, kernel_size, response, grid)
    except OpticsError as e:
        return None, str(e)
    focus = "prescribed focus" if focus_m is None else f"focus {focus_m:.3g} m"
    iris = f"{lens.iris}, " if getattr(lens, "iris", "") else ""
    return PSFSource("olf", f"PSFs from {w.store('Omni-Lens-Field', olf.path)} ({w.lead(lens)}in ray space, {iris}"
                            f"{lib.pixel_pitch_mm * 1000:.4g} um pixels, {lib.kernel_size} x {lib.kernel_size} px, "
                            f"{focus}; no tracing)", lib, str(olf.path)), None


def _try_raymap(lens, pitch, settings, kernel_size, unknown_response, response, grid, w: SourceWords = DEFAULT_WORDS):
    """(PSFSource, None) where the lens's shipped ray map serves the request
    (any focus, f-number, blades, pixel pitch, kernel and rays: ``psf.
    raymap``), else (None, why)."""
    path = for_lens(lens.id).raymap                 # the one registry of what ships (``shipped``)
    if path is None:
        return None, f"no ray map of {w.lens_of(lens)} ships with this engine"
    if unknown_response:
        return None, "a custom spectral response was asked for without its curves"
    try:
        rm = open_raymap(path)
        lib = raymap_library(rm, lens, pitch, settings, kernel_size, response, grid)
    except (OpticsError, InputRangeError) as e:
        return None, str(e)
    focus = "prescribed focus" if lib.settings.focus_distance_m is None else \
        f"focus {lib.settings.focus_distance_m:.3g} m"
    iris = f"{lens.iris}, " if getattr(lens, "iris", "") else ""
    return PSFSource("raymap", f"PSFs from {w.store('ray map', path)} ({w.lead(lens)}{iris}{lib.pixel_pitch_mm * 1000:.4g} um "
                               f"pixels, {lib.kernel_size} x {lib.kernel_size} px, {focus}; no tracing)",
                     lib, None, None, str(path)), None


def raymap_library(rm: RayMap, lens, pitch, settings: PSFSettings | None, kernel_size=None, response=None,
                   grid: LibraryGrid | None = None) -> RayMapLibrary:
    """A library of ``lens`` from its ray map at ``pitch`` (mm; None: the
    lens's sensor) with the request's PSF settings (their focus) and kernel."""
    s = settings or PSFSettings()
    s = replace(s, pixel_pitch_mm=pitch if pitch is not None else s.pixel_pitch_mm)
    if kernel_size is not None:
        s = replace(s, kernel_size=int(kernel_size))
    return RayMapLibrary(rm, lens, s, grid, response)


def _why_not(olf: OmniLensField, lens, pitch, settings, kernel_size, focus_m, custom_response,
             w: SourceWords = DEFAULT_WORDS) -> str | None:
    """None if ``olf`` covers the request, else the reason (one phrase)."""
    f, it = w.file("Omni-Lens-Field", olf.path), w.lens_of(lens)
    if olf.variant != "radial":
        return f"{f} is a {olf.variant!r} OLF (the renderer takes radial ones)"
    if lens.id not in olf.lens_ids:
        return f"{f} did not learn {w.quoted(lens)} (it learned {', '.join(w.name(i) for i in olf.lens_ids)})"
    if not olf.covers(lens):
        return _stopped_down(lens, "Omni-Lens-Field", olf.path, w) or (
            f"{w.lens_of(lens, file=True)} differs optically from the prescription {f} learned "
                "(changed prescription: not served)")
    entry = olf.lens_entry(lens.id)
    learned = float(entry["pixel_pitch_mm"])
    if pitch is not None and not (pitch >= learned or same_pitch(pitch, learned)):
        return (f"the image's pixel pitch {pitch * 1000:.6g} um is finer than the {learned * 1000:.6g} um "
                f"{f} learned {it} at (its kernels are area-resampled to coarser pitches only: "
                "a finer one would invent detail)")
    k = resampled_size(int(entry["kernel_size"]), learned, learned if pitch is None else pitch)
    if kernel_size is not None and kernel_size != k:
        return f"a {kernel_size} px kernel was asked for; {f} serves {it} at {k} px at this pitch"
    if custom_response:
        return "a custom spectral response was given; the OLF learned the shipped one"
    diff = _settings_differences(entry["psf_settings"], settings)
    if diff:
        return "PSF settings differ from the learned ones: " + "; ".join(diff)
    fr = entry.get("focus_range_m")
    if focus_m is not None and not fr:
        return f"focus {focus_m:.3g} m asked for; {f} learned {it} at its prescribed focus only"
    if fr:
        try:
            olf.focus_diopters(lens.id, focus_m)
        except InputRangeError:
            if focus_m is None:
                return f"{f} learned {it} across focus distances but not its prescribed focus; give one"
            return f"focus {focus_m:g} m is outside the learned {fr[0]:g} m to {fr[1]:g} m"
    return None


__all__ = ["BasisLibrary", "OLFLibrary", "PSFSource", "SourceWords", "psf_source", "shipped_olf_files", "SHIPPED", "WEIGHTS_DIR", "SOURCES"]


def lens_library(lens, geometry, settings: PSFSettings | None = None, grid: LibraryGrid | None = None, *,
                 response=None, cache: bool = True, fit_depth_m=None, progress=None) -> PSFLibrary:
    """The lens's own PSFs at the image's pixel pitch for a renderer that is
    given none (``render.simulate``, ``render.bokeh``, ``correct.
    deconvolution``): no stored approximation of them (a basis, an OLF),
    the source a job would choose otherwise: deposited from the lens's ray
    map where one ships and serves these settings, else traced
    (``open_library``: the arguments are its)."""
    s = settings or PSFSettings()
    if s.pixel_pitch_mm is not None and not math.isclose(s.pixel_pitch_mm, geometry.pixel_pitch_mm, rel_tol=SAME_GIVEN_RTOL):
        raise InputRangeError("pixel pitch", s.pixel_pitch_mm,
                              f"{geometry.pixel_pitch_mm:.6g} mm, the image's own pixel pitch (give one, not two)")
    src, _ = _try_raymap(lens, geometry.pixel_pitch_mm, s, None, False, response, grid)
    if src is not None:
        return src.library.at_geometry(geometry, s, fit_depth_m=fit_depth_m, progress=progress)
    return open_library(lens, geometry, s, grid, response=response, cache=cache, fit_depth_m=fit_depth_m,
                        progress=progress)


# Traced PSFs for a preview (the add-on's viewport) where no shipped basis or
# OLF holds the request: fewer pupil rays and wavelengths, a proxy of the
# render's (docs/addon.md gives its error and time against the full trace).
PREVIEW_TRACE = {"pupil_samples": 24, "n_wavelengths": 9}


@dataclass(frozen=True)
class PSFRequest:
    """Which PSFs a job asks for.

    ``source``: 'basis', 'raymap', 'olf', 'trace' or None (the source rule,
    ``psf.rule``). ``olf_file`` / ``basis_file``:
    files instead of the shipped ones. ``settings``: the PSF settings (their
    ``focus_distance_m`` the focus, metres, None: as prescribed; their pitch
    is the image's). ``kernel_size``: an explicit kernel (px; None: the
    settings', grown to hold the blur where ``fit_kernel``). ``response``:
    the sensor's spectral response (None: the shipped curves). ``preview``:
    PSFs that must be traced are traced with :data:`PREVIEW_TRACE`.
    ``field_step_px``: an OLF's or a trace's fields at most this many image
    pixels apart (``sampling.field_grid``; None: the source's own grid).
    ``focus_tolerance_px``: the focus may be rounded (``sampling.snap_focus``)
    by at most this many pixels of blur diameter, so that nearby focus
    distances share PSFs (None: the focus as asked; a job applies it).
    ``max_error_db``: the job's error budget (``psf.budget``: dB PSNR against
    the render with converged PSFs; None: the settings as given). A job
    whose source is a ray map or a trace plans its rays, wavelengths and
    field step by it, keeping the knobs named in ``fixed`` (``budget.KNOBS``)
    as the request gives them; a stored source (basis, OLF) serves as it is.
    ``words``: how the source's message names files and lenses
    (:class:`SourceWords`; None: by path and id)."""

    source: str | None = None
    olf_file: str | None = None
    basis_file: str | None = None
    settings: PSFSettings | None = None
    kernel_size: int | None = None
    response: object = None
    fit_kernel: bool = True
    preview: bool = False
    field_step_px: float | None = None
    focus_tolerance_px: float | None = None
    max_error_db: float | None = None
    fixed: tuple = ()
    words: SourceWords | None = None

    def __post_init__(self):
        from .budget import KNOBS, check_budget
        object.__setattr__(self, "max_error_db", check_budget(self.max_error_db))
        unknown = [k for k in self.fixed if k not in KNOBS]
        if unknown:
            raise InputRangeError("fixed", unknown[0], f"some of {', '.join(KNOBS)}")
        object.__setattr__(self, "fixed", tuple(self.fixed))
        for name in ("field_step_px", "focus_tolerance_px"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputRangeError(name, v, "> 0 pixels and finite, or None")
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
    """The PSFs serving a job: ``kind`` ('basis', 'raymap', 'olf' or
    'trace'), why (``message``, one line), ``library`` (always set), the
    files and the ``quality`` ('full'; 'preview' for a preview's lighter
    trace or ray map; 'planned' where the job's error budget chose the PSF
    work, ``psf.budget``)."""

    kind: str
    message: str
    library: object
    olf_file: str | None = None
    basis_file: str | None = None
    quality: str = "full"
    raymap_file: str | None = None

    def as_dict(self) -> dict:
        return {"psf_source": self.kind, "psf_message": self.message, "psf_quality": self.quality,
                "olf_file": self.olf_file if self.kind == "olf" else None,
                "basis_file": self.basis_file if self.kind == "basis" else None}


def choose(lens, geometry, request: PSFRequest) -> PSFSource:
    """``psf_source``'s choice for a job's request at ``geometry``'s pixel pitch (mm)."""
    return psf_source(lens, source=request.source, olf_file=request.olf_file, basis_file=request.basis_file,
                      pixel_pitch_mm=geometry.pixel_pitch_mm, settings=request.settings,
                      kernel_size=request.kernel_size, focus_m=request.focus_m,
                      custom_response=request.response is not None,
                      olf_grid=_request_grid(lens, geometry, request), response=request.response,
                      words=request.words)


def _request_grid(lens, geometry, request: PSFRequest) -> LibraryGrid | None:
    """The grid an OLF or a trace samples for ``request`` (None: its own)."""
    return field_grid(None, lens.sensor.semi_diagonal_mm, geometry.pixel_pitch_mm, request.field_step_px)


def open_source(lens, geometry, request: PSFRequest, *, fit_depth_m=None, control: Control | None = None,
                chosen=None) -> PSFSourceResult:
    """The PSFs of ``lens`` for an image at ``geometry`` as ``request`` asks
    (``PSFSource.at``); ``chosen``: the source already chosen for this
    request (``psf_source``'s), not chosen again."""
    src = chosen if chosen is not None else choose(lens, geometry, request)
    return src.at(geometry, request, fit_depth_m=fit_depth_m, control=control)


def ensure_bins(library, depth_m, control: Control | None = None) -> None:
    """Compute now the depth bins the valid depths of ``depth_m`` (metres)
    interpolate from, so that progress and cancel work while PSFs are built.
    Only the bins the frame holds: a bin between two of them that no pixel
    touches (a subject and the far background) is made only if a patch's
    mean inverse depth falls in it, when the renderer asks for it."""
    d = np.asarray(depth_m, np.float64)
    d = d[d > 0]                    # NaN, 0 and negative depths are left sharp
    if d.size == 0:
        return
    control = control or Control()
    library.ensure(bins=library.bins_needed(d, clamp_near=True), progress=control.counter("PSFs"))
