"""The PSF library: RGB PSFs over fields x depths, cached on disk, built lazily.

Rotational symmetry: one radial line of fields (normalised image height 0..1
along sensor +y) is enough; a renderer rotates each kernel to its azimuth.
Depth bins are uniform in inverse depth (diopters) from ``near_m`` to
``far_m`` plus infinity; as docs/design.md fixes, any depth at or beyond ``far_m``
(including ``inf`` and Blender's 1e10 background) uses the infinity PSF. A
depth below ``near_m`` is an error unless the caller asks to clamp it.

Interpolation is linear in field and in inverse depth. Only the depth bins
that a query (a list of depths or a depth map) touches are computed; results
are cached in a file keyed by the lens's optical content and every setting,
written atomically and checked on load (checksum, key, shapes, finiteness):
a corrupt or stale cache is rebuilt, never used. A cache that cannot be
written (a full disk, a read-only folder) costs the job nothing but the
time next run: one warning, and the PSFs stay in memory.

What the normalisation of each kernel hides travels with it: the energy
outside the k x k window (``energy_outside``) and the kernel that would
hold 99 % of the rays (``kernel_size_needed``) are arrays of the cache file
and of a library file like the kernels, so a library that serves clipped
kernels says so whether it traced them now or read them (``ensure``).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
import warnings
import weakref
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..atomic import active, atomic_path
from ..outputs import default_cache_dir
from ..optics.aiming import sources
from ..errors import InputRangeError, OutputError, field, output_error
from ..optics.errors import OpticsError
from ..optics.lens import Lens, lens_fingerprint
from .compute import (CLIP_WARNING, KernelTooSmallWarning, PSFSettings, check_psf_memory, clip_message, compute_sources, focused_lens, pixel_pitch_mm,
                      spectral_samples)
from .pitch import SAME_GIVEN_RTOL
from .spectral import SpectralResponse, default_response
from ..io.jsontext import loads

FORMAT_VERSION = 1
# bumped whenever the PSF computation changes what it produces
ALGORITHM_VERSION = 3     # 2: rays into the pixel they land in (deposit_sigma_px), not a Gaussian; 3: over their footprint


class CacheWarning(UserWarning):
    """A cache file was unusable (corrupt or stale) and is being rebuilt, or
    could not be written (the PSFs then stay in memory)."""


@dataclass(frozen=True)
class LibraryGrid:
    """Where the library samples: ``n_fields`` fields over [0, 1] and
    ``n_depths`` finite depth bins uniform in 1/depth over [near_m, far_m],
    plus infinity."""

    n_fields: int = 64
    n_depths: int = 20
    near_m: float = 0.7
    far_m: float = 10.0

    def __post_init__(self):
        if self.n_fields < 2:
            raise InputRangeError("n_fields", self.n_fields, ">= 2")
        if self.n_depths < 2:
            raise InputRangeError("n_depths", self.n_depths, ">= 2 (near and far at least)")
        if not (0 < self.near_m < self.far_m < math.inf):
            raise InputRangeError(f"{field('near_m')}, {field('far_m')}", (self.near_m, self.far_m),
                                  "0 < near < far < inf metres")

    @property
    def fields(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, self.n_fields)

    @property
    def diopters(self) -> np.ndarray:
        """Inverse depths of the bins (1/m), decreasing, the last one 0 (infinity)."""
        return np.append(np.linspace(1.0 / self.near_m, 1.0 / self.far_m, self.n_depths), 0.0)

    @property
    def depths_m(self) -> np.ndarray:
        d = self.diopters
        with np.errstate(divide="ignore"):
            return np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), np.inf)


class PSFLibrary:
    """PSFs of one lens over ``grid`` (depth bins x fields), computed on demand.

    Arrays (first axis: depth bin, last bin = infinity; second: field):
    ``psf`` (D+1, F, 3, k, k) float32; ``energy_outside`` and
    ``vignetted_fraction`` (D+1, F, 3); ``relative_illumination``,
    ``chief_ray_height_mm``, ``zero_energy``, ``kernel_size_needed`` (D+1, F);
    ``computed`` (D+1,) says which bins hold data, ``served`` which of them
    :meth:`ensure` has served (what its clipping warning speaks of).
    """

    ARRAYS = ("psf", "energy_outside", "vignetted_fraction", "relative_illumination",
              "chief_ray_height_mm", "zero_energy", "kernel_size_needed", "computed")

    def __init__(self, lens: Lens | None, settings: PSFSettings, grid: LibraryGrid,
                 response: SpectralResponse | None, *, cache_dir: str | os.PathLike | None = None,
                 meta: dict | None = None):
        self.lens = lens
        self.settings = settings
        self.grid = grid
        self.response = response
        self.fields = grid.fields
        self.depths_m = grid.depths_m
        self.diopters = grid.diopters
        if meta is None:
            wl, w = spectral_samples(settings, response)
            resp = response or default_response()
            self.lens_fingerprint = lens_fingerprint(lens)
            meta = {
                "format": FORMAT_VERSION, "algorithm": ALGORITHM_VERSION,
                "lens_id": lens.id, "lens_file": lens.path, "lens_fingerprint": self.lens_fingerprint,
                "settings": settings.as_dict(), "grid": asdict(grid),
                "pixel_pitch_mm": pixel_pitch_mm(focused_lens(lens, settings), settings),
                "wavelengths_nm": wl.tolist(), "channel_weights": w.tolist(),
                "response": {"name": resp.name, "source": resp.source, "sha256": resp.content_hash(),
                             "wavelength_nm": resp.wavelength_nm.tolist(), "rgb": resp.rgb.tolist()},
            }
        self.meta = meta
        self.key = hashlib.sha256(json.dumps(
            {k: meta[k] for k in ("format", "algorithm", "lens_fingerprint", "settings", "grid")}
            | {"response": meta["response"]["sha256"]}, sort_keys=True).encode()).hexdigest()
        k = settings.kernel_size
        nd, nf = len(self.depths_m), len(self.fields)
        self.psf = np.zeros((nd, nf, 3, k, k), np.float32)
        self.energy_outside = np.zeros((nd, nf, 3))
        self.vignetted_fraction = np.zeros((nd, nf, 3))
        self.relative_illumination = np.zeros((nd, nf))
        self.chief_ray_height_mm = np.zeros((nd, nf))
        self.zero_energy = np.zeros((nd, nf), bool)
        self.kernel_size_needed = np.zeros((nd, nf), np.int64)
        self.computed = np.zeros(nd, bool)
        # the bins this library has served (ensure): what its clipping warning speaks of
        self.served = np.zeros(nd, bool)
        self._cache_failed = False          # a cache write failed: not tried again
        self._told: set[str] = set()        # what this library has warned outside a job
        # progress(done, total) of the bins computed by ensure() calls that pass none of their own
        self.progress = None
        # a job that answers the clipping itself (a bokeh's large blur) holds the warning until it knows
        self.quiet_clipping = False
        self.cache_path = None
        if cache_dir is not None:
            self.cache_path = Path(cache_dir) / f"{meta['lens_id']}-{self.key[:20]}.npz"
            if self.cache_path.exists():
                self._load_into(self.cache_path)

    # ----------------------------------------------------------- properties
    @property
    def pixel_pitch_mm(self) -> float:
        return float(self.meta["pixel_pitch_mm"])

    @property
    def kernel_size(self) -> int:
        return self.settings.kernel_size

    @property
    def wavelengths_nm(self) -> np.ndarray:
        return np.asarray(self.meta["wavelengths_nm"])

    # ---------------------------------------------------------------- query
    def depth_bins(self, depth_m, *, clamp_near: bool = False):
        """For each depth: (lower bin, upper bin, weight of the upper bin), in
        inverse depth. Depths >= far_m use the infinity bin alone."""
        d = np.asarray(depth_m, dtype=np.float64)
        bad = ~(d > 0)          # NaN, 0, negative
        if bad.any():
            raise InputRangeError("depth_m", float(d[bad].ravel()[0]),
                                  "> 0 metres or inf (mask invalid depths before asking for PSFs)")
        near = self.grid.near_m
        if (d < near).any() and not clamp_near:
            raise InputRangeError("depth_m", float(d.min()),
                                  f">= the library's near limit {near} m (its nearest depth bin)")
        d = np.maximum(d, near)
        far = d >= self.grid.far_m
        x = np.where(far, 0.0, 1.0 / np.where(far, 1.0, d))
        finite = self.diopters[:-1]                       # decreasing
        n = len(finite)
        pos = (finite[0] - x) / (finite[0] - finite[-1]) * (n - 1)
        i0 = np.clip(np.floor(pos).astype(np.int64), 0, n - 2)
        t = np.clip(pos - i0, 0.0, 1.0)
        i1 = np.where(far, n, i0 + 1)
        i0 = np.where(far, n, i0)
        t = np.where(far, 0.0, t)
        return i0, i1, t

    def bins_needed(self, depth_m, *, clamp_near: bool = False) -> np.ndarray:
        """Sorted indices of the depth bins that these depths interpolate from
        (bins whose weight is exactly 0 are left out)."""
        i0, i1, t = self.depth_bins(depth_m, clamp_near=clamp_near)
        # a count per bin, not np.unique: a sort of every pixel's bin cost ~0.5 s at 1920 x 1080
        n = len(self.diopters)
        used = np.bincount(i0[t < 1.0].ravel(), minlength=n) + np.bincount(i1[t > 0.0].ravel(), minlength=n)
        return np.flatnonzero(used)

    def ensure(self, depth_m=None, *, bins=None, clamp_near: bool = False, progress=None) -> list[int]:
        """Compute (or load) the bins that ``depth_m`` needs, or ``bins``;
        returns the bins that were computed now. ``progress(done, total)``
        (default: the library's ``progress`` attribute) is called as PSFs
        are computed."""
        if self.lens is None:
            raise OpticsError("this library was loaded without its lens: it can only serve computed bins")
        want = np.asarray(bins if bins is not None else self.bins_needed(depth_m, clamp_near=clamp_near), int)
        todo = [int(b) for b in want if not self.computed[b]]
        if todo:
            self._compute(todo, progress)
        self.warn_if_clipped(want)
        return todo

    def _compute(self, todo: list[int], progress) -> None:
        """Trace the depth bins ``todo`` and write the cache."""
        lens_f = focused_lens(self.lens, self.settings)
        aimed = sources(lens_f, self.depths_m[todo], field=self.fields)     # (F, n_todo)
        wl, w = np.asarray(self.meta["wavelengths_nm"]), np.asarray(self.meta["channel_weights"])
        plain = replace(self.settings, focus_distance_m=None)
        batch = compute_sources(lens_f, aimed, plain, wl, w, progress=progress or self.progress)
        for j, b in enumerate(todo):
            self.psf[b] = batch.psf[:, j]
            self.energy_outside[b] = batch.energy_outside[:, j]
            self.vignetted_fraction[b] = batch.vignetted_fraction[:, j]
            self.relative_illumination[b] = batch.relative_illumination[:, j]
            self.chief_ray_height_mm[b] = batch.chief_ray_height_mm[:, j]
            self.zero_energy[b] = batch.zero_energy[:, j]
            self.kernel_size_needed[b] = batch.kernel_size_needed[:, j]
            self.computed[b] = True
        self.last_timings_s = batch.timings_s
        if self.cache_path is not None and not self._cache_failed:
            t = time.perf_counter()
            self._write_cache()
            self.last_timings_s["io"] = time.perf_counter() - t

    def _write_cache(self) -> None:
        """Save to the cache file. A cache is an optimisation: where it cannot
        be written (disk full, a read-only folder) the job goes on with the
        PSFs in memory, with one warning (the same text for every library of
        the folder: shown once per job) and no further try by this library."""
        try:
            self.save(self.cache_path)
        except OSError as e:            # OutputError included; a bug's AssertionError is not
            self._cache_failed = True
            err = e if isinstance(e, OutputError) else output_error(self.cache_path, e)
            why = err.raw().removeprefix(f"{err.path}: ")          # the folder named, not each library's file
            self._tell(f"the PSF cache {self.cache_path.parent} could not be written ({why}); the PSFs stay in "
                       "memory for this job", CacheWarning)

    def warn_if_clipped(self, bins=None) -> None:
        """Warn (:class:`~dcdi_core.psf.compute.KernelTooSmallWarning`) when a
        bin this library has served (with ``bins``, served now) holds a
        kernel that clips more than ``CLIP_WARNING`` of a channel's energy:
        the same text whether the bins were traced now or read from the cache
        or a library file, with the worst fraction of the bins served; once
        per job (:meth:`_tell`), again only when worse bins are served."""
        if bins is not None:
            b = np.asarray(bins, int).ravel()
            self.served[b[self.computed[b]]] = True
        text = self.clip_text()
        if text and not self.quiet_clipping:
            self._tell(text, KernelTooSmallWarning)

    def clip_text(self) -> str | None:
        """The clipping warning's text for the bins served so far, or None."""
        held = self.served & self.computed
        return clip_message(self.energy_outside[held], self.kernel_size_needed[held], self.kernel_size,
                            f"PSF library of {self.meta['lens_id']}")

    def _tell(self, text: str, category) -> None:
        """Warn ``text`` once per job: in a `dcdi` command's job
        (``outputs.active()``) once whichever of its libraries repeats it
        (a kernel grown to fit opens a second library in the same cache
        folder); outside one, once per library."""
        job = active()
        told = _job_told(job) if job is not None else self._told
        if text in told:
            return
        told.add(text)
        # a fresh registry: this rule, not the warnings module's once-per-line memory (which a
        # process keeps across jobs), decides; the filters (ignore, error) still apply
        caller = _frame(3)                   # who asked for the PSFs (ensure's caller), as stacklevel would
        warnings.warn_explicit(text, category, caller.f_code.co_filename, caller.f_lineno,
                               module=caller.f_globals.get("__name__"), registry={})

    def build(self, progress=None) -> list[int]:
        """Compute every bin."""
        return self.ensure(bins=np.arange(len(self.depths_m)), progress=progress)

    def field_weights(self, field):
        f = np.asarray(field, dtype=np.float64)
        if not np.isfinite(f).all() or (f < 0).any() or (f > 1.0 + 1e-9).any():
            raise InputRangeError("field", float(np.nanmax(np.abs(f))), "[0, 1] (1 = sensor half-diagonal)")
        pos = np.clip(f, 0.0, 1.0) * (len(self.fields) - 1)
        j0 = np.clip(np.floor(pos).astype(np.int64), 0, len(self.fields) - 2)
        return j0, j0 + 1, pos - j0

    def at(self, field, depth_m, *, clamp_near: bool = False) -> np.ndarray:
        """PSFs (..., 3, k, k) at fields x depths (broadcast together), linear in
        field and in inverse depth; computes the bins it needs."""
        field, depth_m = np.broadcast_arrays(np.asarray(field, float), np.asarray(depth_m, float))
        i0, i1, t = self.depth_bins(depth_m, clamp_near=clamp_near)
        self.ensure(bins=np.unique(np.concatenate([i0.ravel(), i1.ravel()])))
        j0, j1, u = self.field_weights(field)
        t = t[..., None, None, None].astype(np.float32)
        u = u[..., None, None, None].astype(np.float32)
        p = self.psf
        lo = (1 - u) * p[i0, j0] + u * p[i0, j1]
        hi = (1 - u) * p[i1, j0] + u * p[i1, j1]
        return (1 - t) * lo + t * hi

    def at_geometry(self, geometry, settings: PSFSettings | None = None, *, fit_depth_m=None,
                    progress=None) -> "PSFLibrary":
        """This lens's PSFs for an image at ``geometry`` (``render.geometry.
        ImageGeometry``: its pixel pitch, mm), made anew by the source of this
        library's kind: traced here, since a stored source (a basis, an OLF)
        holds no kernel wider or finer than its own; a ray map's library from
        its ray map. ``settings``: the PSF settings (default: this library's;
        the pitch is the geometry's); the grid and the spectral response are
        this library's. ``fit_depth_m`` and ``progress`` as
        ``psf.sources.open_library``'s."""
        s = replace(settings or self.settings, pixel_pitch_mm=None)
        return open_library(self.lens, geometry, s, self.grid, response=self.response, fit_depth_m=fit_depth_m,
                            progress=progress)

    # -------------------------------------------------------------- storage
    def save(self, path: str | os.PathLike) -> None:
        """Write the library (all arrays, metadata and a checksum) atomically."""
        arrays = {name: getattr(self, name) for name in self.ARRAYS}
        meta = dict(self.meta, key=self.key, checksum=_checksum(arrays))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                from ..io.npzfile import save_npz
                save_npz(f, {"meta": np.array(json.dumps(meta)), **arrays})

    def _load_into(self, path: Path, *, cache: bool = True) -> bool:
        """The arrays of ``path`` into this library; False where the file is
        unusable. ``cache``: the file is the disk cache's own (dropped, with
        a warning, to be rebuilt); otherwise it is the user's file, never
        touched, and the reason is raised (OpticsError)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = loads(str(z["meta"]), path)
                arrays = {name: z[name] for name in self.ARRAYS}
            if meta.get("key") != self.key:
                raise ValueError("key mismatch (stale: lens or settings changed)")
            if meta.get("checksum") != _checksum(arrays):
                raise ValueError("checksum mismatch (corrupt)")
            for name in self.ARRAYS:
                if arrays[name].shape != getattr(self, name).shape:
                    raise ValueError(f"array {name} has shape {arrays[name].shape}")
            if not np.isfinite(arrays["psf"]).all():
                raise ValueError("non-finite PSF values")
        except Exception as e:  # noqa: BLE001 - any failure means: do not use it
            if not cache:
                raise OpticsError(f"{path}: corrupt PSF library file ({e})") from None
            warnings.warn(f"PSF cache {path} is unusable ({e}); rebuilding it", CacheWarning, stacklevel=3)
            try:
                path.unlink()
            except OSError:
                pass
            return False
        for name in self.ARRAYS:
            getattr(self, name)[...] = arrays[name]
        return True

    @classmethod
    def open(cls, lens: Lens, settings: PSFSettings | None = None, grid: LibraryGrid | None = None,
             response: SpectralResponse | None = None, *, cache: bool = True,
             cache_dir: str | os.PathLike | None = None) -> "PSFLibrary":
        """The library of ``lens`` for these settings, backed by the disk cache."""
        cd = (cache_dir or default_cache_dir()) if cache else None
        return cls(lens, settings or PSFSettings(), grid or LibraryGrid(), response, cache_dir=cd)

    @classmethod
    def load(cls, path: str | os.PathLike, lens: Lens | None = None) -> "PSFLibrary":
        """A library file written by :meth:`save` (``dcdi psflib build -o``).
        Without ``lens`` it serves only the bins it holds."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [n for n in ("meta", *cls.ARRAYS) if n not in z.files]
                if missing:             # another .npz: a ray map, a basis, an image's arrays
                    raise OpticsError(f"{path}: not a PSF library file (it holds no {', '.join(missing[:3])}; "
                                      "`dcdi psflib build -o` writes one)")
                meta = loads(str(z["meta"]), path)
                shapes = {name: _stored_shape(z, name) for name in cls.ARRAYS}
            s = dict(meta["settings"])
            s["band_nm"] = tuple(s["band_nm"])
            settings = PSFSettings(**s)
            grid = LibraryGrid(**meta["grid"])
            fingerprint = str(meta["lens_fingerprint"])
        except OpticsError:
            raise
        except KeyError as e:           # metadata without a part the reader needs
            raise OpticsError(f"{path}: not a PSF library file (its metadata has no {e.args[0]!r})") from None
        except Exception as e:  # noqa: BLE001 - a file that is not one of ours, or damaged: said, never used
            raise OpticsError(f"{path}: not a PSF library file ({e})") from None
        # what the file declares is allocated only where its own arrays hold that much (a 20 KB file declaring a
        # grid of millions of PSFs is refused here, not after gigabytes) and it fits in memory
        want = (grid.n_depths + 1, grid.n_fields, 3, settings.kernel_size, settings.kernel_size)
        if shapes["psf"] != want:
            raise OpticsError(f"{path}: corrupt PSF library file (its PSFs have shape {shapes['psf']}; its settings "
                              f"and grid declare {want})")
        check_psf_memory(settings, 1, library_psfs=grid.n_fields * (grid.n_depths + 1))
        if lens is not None and lens_fingerprint(lens) != fingerprint:
            raise OpticsError(f"{path}: built for another lens or version of it "
                              f"({meta.get('lens_id')}, {meta.get('lens_file')})")
        lib = cls(lens, settings, grid, None, meta=meta)
        lib._load_into(path, cache=False)             # the user's file: a damaged one is said, never deleted
        return lib


def _stored_shape(z, name: str) -> tuple:
    """The shape of array ``name`` in the open .npz ``z``, from its header
    alone (nothing of it is read)."""
    with z.zip.open(f"{name}.npy") as f:
        version = np.lib.format.read_magic(f)
        shape, _, _ = np.lib.format._read_array_header(f, version)
    return tuple(shape)


def _frame(depth: int):
    """The frame ``depth`` calls above the caller's, or the outermost one where
    the stack is shallower."""
    frame = sys._getframe(1)
    for _ in range(depth):
        if frame.f_back is None:
            break
        frame = frame.f_back
    return frame


# the texts each running job has been told: {id(job): (weak reference to the job, texts)}
_TOLD: dict[int, tuple[weakref.ref, set]] = {}


def _job_told(job) -> set:
    """The warning texts ``job`` (an ``outputs.JobFiles``) has been told; the
    entries of finished jobs are dropped."""
    for key in [k for k, (ref, _) in _TOLD.items() if ref() is None]:
        del _TOLD[key]
    entry = _TOLD.get(id(job))
    if entry is None or entry[0]() is not job:
        entry = _TOLD[id(job)] = (weakref.ref(job), set())
    return entry[1]


def _checksum(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def valid_depth_mask(depth: np.ndarray) -> np.ndarray:
    """True where a depth value is usable: > 0 (inf included), not NaN."""
    return depth > 0


MAX_FITTED_KERNEL = 129      # px: beyond this a patch-wise FFT blur costs more than it is worth here


def open_library(lens, geometry, settings: PSFSettings | None = None,
                 grid: LibraryGrid | None = None, *, response=None, cache: bool = True, fit_depth_m=None,
                 progress=None, kept: dict | None = None) -> PSFLibrary:
    """The lens's PSF library sampled at the image's pixel pitch.

    settings.pixel_pitch_mm, if set, must be the geometry's (the PSFs of an
    image are sampled at its own pitch). response: the sensor's spectral
    response (default: the shipped one).
    fit_depth_m: a depth map (metres) whose depth bins are computed now; if
    their PSFs spill out of the settings' kernel (less than 99 % of the rays
    inside, as a fast lens's defocus blur at full resolution does), the
    library is reopened with the odd kernel size that holds them, at most
    MAX_FITTED_KERNEL px (beyond that the usual KernelTooSmallWarning says
    how much is clipped). Without it the kernel size is the settings'.
    progress(done, total): called as PSF bins are computed. ``kept``: the
    libraries already opened for this lens, grid and response, by their
    settings (``psf.sources.PSFSource.opened``): one of the same settings is
    served with the bins it holds; those opened here are added."""
    s = settings or PSFSettings()
    if s.pixel_pitch_mm is not None and not math.isclose(s.pixel_pitch_mm, geometry.pixel_pitch_mm, rel_tol=SAME_GIVEN_RTOL):
        raise InputRangeError("pixel pitch", s.pixel_pitch_mm,
                              f"{geometry.pixel_pitch_mm:.6g} mm, the image's own pixel pitch (give one, not two)")
    s = replace(s, pixel_pitch_mm=geometry.pixel_pitch_mm)

    def make(st):
        if kept is None:
            return PSFLibrary.open(lens, st, grid, response, cache=cache)
        key = (st, grid, None if response is None else id(response), cache)
        if key not in kept:
            kept[key] = PSFLibrary.open(lens, st, grid, response, cache=cache)
        return kept[key]
    return _fitted(make, s, fit_depth_m, progress)


def _fitted(make, settings: PSFSettings, fit_depth_m, progress):
    """``make(settings)``'s library; with a depth map ``fit_depth_m``, its bins
    computed now and, where their PSFs spill out of the kernel (less than
    99 % of the rays inside), made again with the odd kernel that holds them,
    at most MAX_FITTED_KERNEL px."""
    library = make(settings)
    library.progress = progress
    if fit_depth_m is None:
        return library
    d = np.asarray(fit_depth_m, dtype=np.float64)
    d = d[valid_depth_mask(d)]
    if d.size == 0:
        return library
    _ensure_quietly(library, d, progress)              # a clipping kernel is answered below by a larger one
    need = int(library.kernel_size_needed[library.computed].max())
    if need <= library.kernel_size or library.kernel_size >= MAX_FITTED_KERNEL:
        return library
    library = make(replace(settings, kernel_size=min(need | 1, MAX_FITTED_KERNEL)))
    library.progress = progress
    _ensure_quietly(library, d, None)                  # what still clips is warned when the bins are served
    computed = library.computed
    if library.kernel_size < MAX_FITTED_KERNEL and library.energy_outside[computed].max() > CLIP_WARNING:
        # 99 % of the rays inside can leave more than CLIP_WARNING of a channel's light out (a fast lens's
        # halo, its wavelengths weighed unequally: the Sonnar's 95 px left 1.4 %): one step a sixth wider
        library = make(replace(settings, kernel_size=min(int(library.kernel_size * 7 / 6) | 1, MAX_FITTED_KERNEL)))
        library.progress = progress
        _ensure_quietly(library, d, None)
    return library


def _ensure_quietly(library: PSFLibrary, depth_m, progress) -> None:
    """``library.ensure(depth_m)`` with its clipping warning held (``quiet_clipping``):
    the renderer that serves the bins warns, or answers it (a bokeh's large blur)."""
    quiet, library.quiet_clipping = library.quiet_clipping, True
    try:
        library.ensure(depth_m, clamp_near=True, progress=progress)
    finally:
        library.quiet_clipping = quiet
