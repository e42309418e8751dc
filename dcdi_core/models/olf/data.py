"""Training and held-out samples for the Omni-Lens-Field, from the project's
ray-traced PSFs, or (``source`` 'raymap') from a lens's shipped ray map.

``source`` 'raymap': the grid's libraries and the off-grid training points
of a lens with a shipped ray map are deposited from it (``psf.raymap``: the
rays the tracer would launch, from the map's polynomials: any focus, no
tracing); a lens without one is traced. Held-out points are always traced,
with ``held_out_rays`` per pupil side (None: the training's), so that the
score is against the lens and not against the map.

Three sets per lens:

- the grid: the PSF library's own samples (fields x depth bins [x focus
  bins]), read from its disk cache or traced once;  a lens learned across
  focus has one library per focus bin (uniform in diopters over
  ``focus_range_m``, infinity allowed) plus its prescribed one, whose focus
  is encoded at the paraxial focus its sensor position is equivalent to
  (``optics.paraxial.prescribed_focus_diopters``);
- off-grid training points: (field, depth[, focus]) drawn at random and
  traced freshly with the library's settings, so the network learns the
  field and not the grid;
- held-out points: drawn and traced the same way from another seed, never
  trained on.

``radial``: targets are the radial kernels (rows along the radial direction)
cropped to the lens's k and renormalised to sum 1 per channel. k is the
smallest odd size whose centred square holds ``energy`` (99 %) of every
PSF's arriving energy over the lens's depth (and focus) range; where 41 px
clip more than that, the library is rebuilt at the size the rays need
(``kernel_size_needed``), at most ``max_kernel``.

``paper``: the paper's grid of 16-px patches of a 1280 x 1920 image, depths
0.7-10 m in 0.1 m steps, 41-px kernels in image orientation, peak-normalised
per channel. Targets are the library's kernels interpolated to the patch
centre's field and the depth (linear in field and inverse depth, the
library's error 0.0014-0.0020) and rotated to the patch's azimuth
(``render.psfmap.rotate_radial_kernels``); off-grid and held-out points are
fractional patch positions at depths uniform in diopters, traced.

Everything here is numpy; the trainer turns batches into tensors.
"""
from __future__ import annotations

import hashlib
import json
import math
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ...atomic import atomic_path
from ...optics.aiming import solve_field
from ...errors import InputRangeError
from ...optics.lens import Lens, load_lens
from ...optics.paraxial import prescribed_focus_diopters
from ...psf.compute import (KernelTooSmallWarning, PSFSettings, compute_sources, focused_lens,
                            spectral_samples)
from ...psf.library import ALGORITHM_VERSION, LibraryGrid, PSFLibrary
from ...optics.lens import lens_fingerprint
from ...render.geometry import ImageGeometry
from ...render.psfmap import rotate_radial_kernels, support_radius
from .spec import PAPER_GRID, OLFSpec, check_variant_and_lenses
from ...psf.olf import encode_paper, encode_radial, inverse_depth, patch_centres_px

PAPER_KERNEL = 41
PAPER_DEPTHS_M = np.round(np.arange(0.7, 10.0 + 1e-9, 0.1), 1)     # the paper's 94 depths
INFINITY_FRACTION = 0.1          # radial off-grid / held-out points drawn at infinity
MAX_DEPOSIT_SIGMA_PX = 5.0       # a ray's Gaussian spread beyond this blurs the PSF itself


@dataclass(frozen=True)
class PSFDataConfig:
    """What the OLF learns from (all of it decides the samples)."""

    lenses: tuple[str, ...]
    variant: str = "radial"
    # PSF computation (PSFSettings) and the library's grid (LibraryGrid)
    pupil_samples: int = 64
    n_wavelengths: int = 31
    n_fields: int = 64
    n_depths: int = 20
    near_m: float = 0.7
    far_m: float = 10.0
    # radial only: lenses learned across focus, focus range (m; far may be inf)
    # and library focus bins (uniform in diopters; the prescribed focus besides)
    focus_lenses: tuple[str, ...] = ()
    focus_range_m: tuple[float, float] = (0.7, math.inf)
    focus_bins: int = 3
    # traced points per lens
    offgrid: int = 256
    held_out: int = 64
    offgrid_fraction: float = 0.25     # of each batch
    # where the training PSFs come from ('trace', or 'raymap': a lens's shipped ray map where it has one) and
    # the rays per pupil side of the traced held-out points (None: pupil_samples)
    source: str = "trace"
    held_out_rays: int | None = None
    # the pitch the network learns at (mm; None: each lens's sensor pixels); coarser ones are area-resampled
    pixel_pitch_mm: float | None = None
    # each ray's Gaussian spread (px) in every PSF, learned and held out (PSFSettings.deposit_sigma_px): 0 is
    # the ray histogram, whose ray-grid moire differs between ray counts; the paper's sqrt(2)/3 smooths it
    deposit_sigma_px: float = 0.0
    # kernels
    kernel_size: int | None = None     # radial: None = per lens (energy); paper: 41
    energy: float = 0.99
    max_kernel: int = 129
    seed: int = 0

    def __post_init__(self):
        object.__setattr__(self, "lenses", tuple(self.lenses))
        object.__setattr__(self, "focus_lenses", tuple(self.focus_lenses))
        object.__setattr__(self, "focus_range_m", tuple(float(v) for v in self.focus_range_m))
        check_variant_and_lenses(self.variant, self.lenses)
        unknown = set(self.focus_lenses) - set(self.lenses)
        if unknown:
            raise InputRangeError("focus_lenses", sorted(unknown), f"a subset of the lenses {self.lenses}")
        if self.focus_lenses and self.variant != "radial":
            raise InputRangeError("focus_lenses", self.focus_lenses, "empty for the paper variant")
        lo, hi = self.focus_range_m
        if not (0 < lo < hi and math.isfinite(lo)):
            raise InputRangeError("focus_range_m", self.focus_range_m, "0 < near < far metres (far may be inf)")
        if self.focus_lenses and self.focus_bins < 2:
            raise InputRangeError("focus_bins", self.focus_bins, ">= 2")
        if self.offgrid < 0 or self.held_out < 1:
            raise InputRangeError("offgrid, held_out", (self.offgrid, self.held_out), "offgrid >= 0, held_out >= 1")
        if not (0.0 <= self.offgrid_fraction < 1.0):
            raise InputRangeError("offgrid_fraction", self.offgrid_fraction, "[0, 1)")
        if self.source not in ("trace", "raymap"):
            raise InputRangeError("source", self.source, "trace or raymap")
        p = self.pixel_pitch_mm
        if p is not None and not (isinstance(p, (int, float)) and math.isfinite(p) and p > 0):
            raise InputRangeError("pixel_pitch_mm", p, "a pixel pitch > 0 mm, or None (each lens's sensor)")
        g = self.deposit_sigma_px
        if not (isinstance(g, (int, float)) and 0.0 <= g <= MAX_DEPOSIT_SIGMA_PX):
            raise InputRangeError("deposit_sigma_px", g, f"0 to {MAX_DEPOSIT_SIGMA_PX} px")
        if self.held_out_rays is not None and self.held_out_rays < 2:
            raise InputRangeError("held_out_rays", self.held_out_rays, ">= 2 rays per pupil side, or None")
        if not (0.5 < self.energy <= 1.0):
            raise InputRangeError("energy", self.energy, "(0.5, 1]")
        if self.kernel_size is not None and (self.kernel_size < 1 or self.kernel_size % 2 == 0):
            raise InputRangeError("kernel_size", self.kernel_size, "an odd integer >= 1, or None (radial: per lens)")
        LibraryGrid(self.n_fields, self.n_depths, self.near_m, self.far_m)   # validates

    def psf_settings(self, kernel_size: int, focus_m: float | None = None) -> PSFSettings:
        return PSFSettings(kernel_size=kernel_size, pupil_samples=self.pupil_samples,
                           n_wavelengths=self.n_wavelengths, focus_distance_m=focus_m,
                           pixel_pitch_mm=self.pixel_pitch_mm, deposit_sigma_px=float(self.deposit_sigma_px))

    @property
    def grid(self) -> LibraryGrid:
        return LibraryGrid(self.n_fields, self.n_depths, self.near_m, self.far_m)

    @property
    def focus_diopters_range(self) -> tuple[float, float]:
        """The learned focus range in diopters (1/m): (1/far, 1/near); 0 is infinity."""
        lo, hi = self.focus_range_m
        return 1.0 / hi, 1.0 / lo

    def focus_values_m(self, lens_id: str) -> list[float | None]:
        """The library focus values of a lens: [None] (the prescribed focus),
        then, for a focus lens, its bins uniform in diopters (inf where 0 D)."""
        if lens_id not in self.focus_lenses:
            return [None]
        d_lo, d_hi = self.focus_diopters_range
        return [None] + [math.inf if v == 0 else float(1.0 / v)
                         for v in np.linspace(d_hi, d_lo, self.focus_bins)]

    def as_dict(self) -> dict:
        d = asdict(self)
        for k in ("lenses", "focus_lenses", "focus_range_m"):
            d[k] = list(d[k])
        if not d["deposit_sigma_px"]:        # the histogram: a run's settings and points as before the field
            del d["deposit_sigma_px"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PSFDataConfig":
        return cls(**d)

    def raymap(self, lens: Lens):
        """The lens's shipped ray map where ``source`` is 'raymap' and one ships, else None (traced)."""
        if self.source != "raymap":
            return None
        from ...psf.raymap import open_raymap
        from ...shipped import raymap_file
        path = raymap_file(lens.id)
        return None if path is None else open_raymap(path)


@dataclass
class LensSamples:
    """The samples of one lens. Inputs are encoded (``psf.olf``)."""

    lens: Lens
    index: int
    kernel_size: int
    libraries: list                      # one PSFLibrary per focus value
    focus_values_m: list
    pixel_pitch_mm: float
    energy_held: float                   # min fraction of a PSF's energy inside k x k (grid)
    grid_x: np.ndarray | None = None     # radial: (n, n_in) float32
    grid_y: np.ndarray | None = None     # radial: (n, 3, k, k) float32, sum 1
    off_x: np.ndarray = None             # (n, n_in) float32
    off_y: np.ndarray = None             # (n, 3, k, k) float32 (radial: sum 1; paper: peak 1)
    val_x: np.ndarray = None
    val_y: np.ndarray = None
    val_coords: dict = field(default_factory=dict)   # field, depth_m, focus_m[, row, col]
    geometry: ImageGeometry | None = None            # paper: the 1280 x 1920 image on the sensor

    @property
    def n_grid(self) -> int:
        if self.grid_x is not None:
            return len(self.grid_x)
        return (PAPER_GRID["height"] // PAPER_GRID["patch"]) * (PAPER_GRID["width"] // PAPER_GRID["patch"]) \
            * len(self._paper_depths)

    @property
    def _paper_depths(self) -> np.ndarray:
        lib = self.libraries[0]
        d = PAPER_DEPTHS_M
        return d[(d >= lib.grid.near_m - 1e-9) & (d <= lib.grid.far_m + 1e-9)]


@dataclass
class Batch:
    """Samples grouped by lens: a list of (lens index, x (n, n_in) float32,
    y (n, 3, k, k) float32, scale (n, 3) float32); the loss compares y / scale."""

    groups: list


class OLFData:
    """All samples of an OLF run (see the module's docstring)."""

    def __init__(self, config: PSFDataConfig, lenses: list[LensSamples], spec_kw: dict):
        self.config = config
        self.lenses = lenses
        self.spec_kw = spec_kw          # variant, lenses, kernel_sizes, focus, diopter_scale

    # ---------------------------------------------------------------- spec
    def spec(self, size: str | None = None, **kw) -> OLFSpec:
        if size is not None:
            return OLFSpec.sized(size=size, **self.spec_kw, **kw)
        return OLFSpec(**self.spec_kw, **kw)

    @property
    def spec_dict(self) -> dict:
        return OLFSpec(**self.spec_kw).as_dict()

    def lens_metadata(self) -> list[dict]:
        """Per lens, what an exported OLF records (fingerprint, kernel, ranges)."""
        c = self.config
        out = []
        for ls in self.lenses:
            lib = ls.libraries[0]
            focus = ls.lens.id in c.focus_lenses
            out.append({
                "id": ls.lens.id, "name": ls.lens.name, "file": str(ls.lens.path),
                "fingerprint": lens_fingerprint(ls.lens), "kernel_size": ls.kernel_size,
                "pixel_pitch_mm": ls.pixel_pitch_mm, "field_range": [0.0, 1.0],
                "depth_range_m": [c.near_m, c.far_m], "infinity": c.variant == "radial",
                "focus_range_m": list(c.focus_range_m) if focus else None,
                "focus_diopters_range": list(c.focus_diopters_range) if focus else None,
                "prescribed_focus_diopters": prescribed_focus_diopters(ls.lens) if focus else None,
                "energy_held": ls.energy_held,
                "psf_settings": lib.settings.as_dict() | {"focus_distance_m": None},
                "library_grid": asdict(lib.grid), "psf_algorithm": ALGORITHM_VERSION,
            })
        return out

    # ------------------------------------------------------------- batches
    def sample(self, rng: np.random.Generator, batch: int) -> Batch:
        """A batch of ``batch`` samples: lenses uniformly, then (1 - offgrid_fraction)
        from the grid and the rest from the off-grid traced points. Draws from
        ``rng`` only (the trainer saves its state)."""
        c = self.config
        has_off = all(len(ls.off_x) for ls in self.lenses)
        n_off = int(round(batch * c.offgrid_fraction)) if has_off else 0
        n_grid = batch - n_off
        lens_g = rng.integers(0, len(self.lenses), n_grid)
        lens_o = rng.integers(0, len(self.lenses), n_off)
        groups = []
        for li, ls in enumerate(self.lenses):
            ng = int((lens_g == li).sum())
            no = int((lens_o == li).sum())
            xs, ys = [], []
            if ng:
                if c.variant == "radial":
                    idx = rng.integers(0, len(ls.grid_x), ng)
                    xs.append(ls.grid_x[idx])
                    ys.append(ls.grid_y[idx])
                else:
                    x, y = self._paper_grid_samples(ls, rng, ng)
                    xs.append(x)
                    ys.append(y)
            if no:
                idx = rng.integers(0, len(ls.off_x), no)
                xs.append(ls.off_x[idx])
                ys.append(ls.off_y[idx])
            if xs:
                y = np.concatenate(ys)
                groups.append((li, np.concatenate(xs), y, target_scale(y)))
        return Batch(groups)

    def held_out(self) -> Batch:
        return Batch([(li, ls.val_x, ls.val_y, target_scale(ls.val_y)) for li, ls in enumerate(self.lenses)])

    def _paper_grid_samples(self, ls: LensSamples, rng, n):
        g = PAPER_GRID
        rows = rng.integers(0, g["height"] // g["patch"], n)
        cols = rng.integers(0, g["width"] // g["patch"], n)
        depths = ls._paper_depths[rng.integers(0, len(ls._paper_depths), n)]
        y = paper_targets_from_library(ls, rows, cols, depths)
        x = encode_paper(self.spec_dict, ls.index, rows, cols, depths).astype(np.float32)
        return x, y

    # ------------------------------------------------------------- summary
    def summary(self) -> dict:
        return {"variant": self.config.variant,
                "lenses": {ls.lens.id: {"kernel_size": ls.kernel_size, "grid": ls.n_grid, "offgrid": len(ls.off_x),
                                        "held_out": len(ls.val_x), "energy_held": ls.energy_held}
                           for ls in self.lenses}}


def target_scale(y: np.ndarray) -> np.ndarray:
    """Per sample and channel, the peak of the target (1 where it is all zero):
    the loss and the paper's metrics work on y / peak."""
    p = y.max(axis=(-1, -2))
    return np.where(p > 0, p, 1.0).astype(np.float32)


# ------------------------------------------------------------------ tracing
def trace_points(lens: Lens, settings: PSFSettings, field, depth_m, focus_m=None):
    """Radial PSFs (n, 3, k, k) at paired (field, depth[, focus]) points and a
    mask of those that hold energy. Points are grouped by focus value (one
    refocused lens per value)."""
    field = np.asarray(field, float).ravel()
    depth_m = np.asarray(depth_m, float).ravel()
    focus = np.full(field.shape, np.nan) if focus_m is None else np.asarray(focus_m, float).ravel()
    k = settings.kernel_size
    psf = np.zeros((len(field), 3, k, k), np.float32)
    ok = np.zeros(len(field), bool)
    wl, w = spectral_samples(settings, None)
    keys = np.unique(focus[~np.isnan(focus)]).tolist() + ([None] if np.isnan(focus).any() else [])
    for f in keys:
        sel = np.isnan(focus) if f is None else (focus == f)
        lens_f = focused_lens(lens, replace(settings, focus_distance_m=f))
        aimed = solve_field(lens_f, depth_m[sel] * 1000.0, field[sel] * lens_f.sensor.semi_diagonal_mm)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            b = compute_sources(lens_f, aimed, replace(settings, focus_distance_m=None), wl, w)
        psf[sel] = b.psf
        ok[sel] = ~b.zero_energy
    return psf, ok


def raymap_points(rm, lens: Lens, settings: PSFSettings, field, depth_m, focus_m=None):
    """:func:`trace_points`'s PSFs and mask, deposited from the lens's ray
    map ``rm`` at those very points (``RayMapLibrary.kernels``)."""
    from ...psf.raymap import RayMapLibrary
    field = np.asarray(field, float).ravel()
    depth_m = np.asarray(depth_m, float).ravel()
    focus = np.full(field.shape, np.nan) if focus_m is None else np.asarray(focus_m, float).ravel()
    k = settings.kernel_size
    psf = np.zeros((len(field), 3, k, k), np.float32)
    keys = np.unique(focus[~np.isnan(focus)]).tolist() + ([None] if np.isnan(focus).any() else [])
    for f in keys:
        sel = np.isnan(focus) if f is None else (focus == f)
        lib = RayMapLibrary(rm, lens, replace(settings, focus_distance_m=f))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            psf[sel] = lib.kernels(field[sel], depth_m[sel])
    ok = psf.sum(axis=(-1, -2)).min(axis=-1) > 0
    return psf, ok


def _draw_radial_points(rng, n, config: PSFDataConfig, focus: bool):
    field = rng.uniform(0.0, 1.0, n)
    dio = rng.uniform(1.0 / config.far_m, 1.0 / config.near_m, n)
    depth = np.where(rng.uniform(size=n) < INFINITY_FRACTION, math.inf, 1.0 / dio)
    focus_m = None
    if focus:
        d_lo, d_hi = config.focus_diopters_range
        # a few focus values per set (one refocused lens each), uniform in
        # diopters; the first group at the prescribed focus (NaN)
        groups = max(1, min(8, n // 8))
        dio_f = rng.uniform(d_lo, d_hi, groups)
        values = np.where(dio_f > 0, 1.0 / np.where(dio_f > 0, dio_f, 1.0), math.inf)
        if groups > 1:
            values[0] = np.nan
        focus_m = values[rng.integers(0, groups, n)]
    return field, depth, focus_m


def focus_diopters(lens: Lens, focus_m) -> np.ndarray:
    """The focus input in diopters: 1 / focus (0 at inf); NaN (the prescribed
    focus) at the lens's equivalent paraxial focus."""
    f = np.asarray(focus_m, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.where(np.isnan(f), prescribed_focus_diopters(lens), 1.0 / f)


def _draw_paper_points(rng, n, config: PSFDataConfig):
    g = PAPER_GRID
    rows = rng.uniform(0, g["height"] // g["patch"] - 1, n)
    cols = rng.uniform(0, g["width"] // g["patch"] - 1, n)
    depth = 1.0 / rng.uniform(1.0 / config.far_m, 1.0 / config.near_m, n)
    return rows, cols, depth


CROP_CHUNK = 512                 # kernels normalised at a time (their float64 temporaries stay small)


def crop_normalise(psf: np.ndarray, k: int) -> np.ndarray:
    """Centred k x k crop of kernels (..., 3, K, K), each channel renormalised
    to 1 (float32; summed in float64, ``CROP_CHUNK`` kernels at a time)."""
    r, h = psf.shape[-1] // 2, k // 2
    c = psf[..., r - h:r + h + 1, r - h:r + h + 1]
    flat = c.reshape((-1,) + c.shape[-3:])
    out = np.empty(flat.shape, np.float32)
    for a in range(0, len(flat), CROP_CHUNK):
        x = flat[a:a + CROP_CHUNK].astype(np.float64)
        s = x.sum(axis=(-1, -2), keepdims=True)
        out[a:a + CROP_CHUNK] = np.where(s > 0, x / np.where(s > 0, s, 1.0), 0.0)
    return out.reshape(c.shape)


def peak_normalise(psf: np.ndarray) -> np.ndarray:
    p = psf.max(axis=(-1, -2), keepdims=True)
    return np.where(p > 0, psf / np.where(p > 0, p, 1.0), 0.0).astype(np.float32)


def energy_kernel_size(psf: np.ndarray, outside: np.ndarray, energy: float) -> tuple[int, float]:
    """Smallest odd k whose centred square holds ``energy`` of every kernel's
    arriving energy (kernels (n, 3, K, K) summing to 1 inside K x K, of which
    ``outside`` (n, 3) fell outside), and the least fraction it holds; K if
    even K x K holds less."""
    n, c, K, _ = psf.shape
    r = K // 2
    d = np.arange(K) - r
    cheb = np.maximum(np.abs(d)[:, None], np.abs(d)[None, :]).ravel()
    ring = np.zeros((K * K, r + 1), np.float32)
    ring[np.arange(K * K), cheb] = 1.0
    per_ring = psf.reshape(n * c, K * K).astype(np.float32) @ ring             # (n c, r + 1)
    held = np.cumsum(per_ring.astype(np.float64), axis=1) * (1.0 - outside.reshape(n * c, 1))
    worst = held.min(axis=0)                                                    # per half-width
    ok = np.nonzero(worst >= energy - 1e-9)[0]
    h = int(ok[0]) if ok.size else r
    return 2 * h + 1, float(worst[h])


# ------------------------------------------------------------------- build
def data_key(config: PSFDataConfig, lenses: list[Lens]) -> str:
    """What decides the samples: the config, each lens's optics, the PSF algorithm."""
    d = {"config": config.as_dict(), "fingerprints": [lens_fingerprint(l) for l in lenses],
         "psf_algorithm": ALGORITHM_VERSION, "format": 2}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


# copies of one lens's library kernels held at once while its samples are made: the libraries, their
# concatenation, the kernels with energy, and the cropped targets (float32 each)
LIBRARY_COPIES = 4


def _check_memory(config: PSFDataConfig) -> None:
    """Refuse, before any work, data whose largest lens would not fit in memory
    (its kernels at ``max_kernel``, or ``kernel_size``; ``LIBRARY_COPIES`` copies)."""
    from ...memory import check_fits
    k = config.kernel_size or (config.max_kernel | 1 if config.variant == "radial" else PAPER_KERNEL)
    n_libs = (config.focus_bins + 1) if config.focus_lenses else 1
    kernels = n_libs * config.n_fields * (config.n_depths + 1)
    check_fits(LIBRARY_COPIES * kernels * 3 * k * k * 4.0,
               f"the OLF's PSF data ({n_libs} libraries of {config.n_fields} fields x {config.n_depths + 1} "
               f"depth bins at up to {k} px)",
               "lower --focus-bins, --fields or --depths, or run one training at a time")


def _open_library(lens, config, k, focus_m, cache_dir, progress):
    rm = config.raymap(lens)
    if rm is not None:              # deposited from the ray map: nothing traced, nothing cached
        from ...psf.raymap import RayMapLibrary
        lib = RayMapLibrary(rm, lens, config.psf_settings(k, focus_m), config.grid)
    else:
        lib = PSFLibrary.open(lens, config.psf_settings(k, focus_m), config.grid, cache_dir=cache_dir,
                              cache=cache_dir is not False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        lib.build(progress=progress)
    return lib


def _open_libraries(lens, config, k0, cache_dir, progress, say):
    """The lens's libraries (one per focus value, the prescribed first) at one
    kernel size, and that size: k0, or (radial, per-lens k) the size the rays
    of any of them need, at most ``max_kernel``. A library that needs more
    than the current size restarts the set at the larger one, so focus bins
    are built once at the size the prescribed library already showed."""
    auto = config.variant == "radial" and config.kernel_size is None
    values = config.focus_values_m(lens.id)
    k, libs = k0, []
    while len(libs) < len(values):
        f = values[len(libs)]
        lib = _open_library(lens, config, k, f, cache_dir, progress)
        need = int(lib.kernel_size_needed.max())
        if auto and need > k and k < (config.max_kernel | 1):
            k = min(need | 1, config.max_kernel | 1)
            say(f"{lens.id}: the rays need {need} px" + ("" if f is None else f" (focus {f:g} m)")
                + f"; libraries (re)built at {k} px")
            libs = []
            continue
        libs.append(lib)
    return libs, k


def build_data(config: PSFDataConfig, *, cache_dir=None, points_file=None, lenses: dict | None = None,
               progress=None, log=None) -> OLFData:
    """All samples of ``config``. Libraries come from the PSF cache
    (``cache_dir``; None = the default, False = no cache); traced points are
    read from ``points_file`` if it holds this config's (same key), else
    traced and written there. ``lenses``: {id: Lens} to use instead of
    loading the ids (the fingerprints keep them honest)."""
    say = log or (lambda s: None)
    lens_objs = [(lenses or {}).get(lid) or load_lens(lid) for lid in config.lenses]
    key = data_key(config, lens_objs)
    stored = _read_points(points_file, key) if points_file else None
    out = []
    focus = bool(config.focus_lenses)
    diopter_scale = 1.0 / config.near_m
    spec_kw = {"variant": config.variant, "lenses": tuple(config.lenses), "focus": focus,
               "diopter_scale": diopter_scale}
    spec_d = OLFSpec(kernel_sizes=[1] * len(config.lenses), **spec_kw).as_dict()
    n_inputs = OLFSpec(kernel_sizes=[1] * len(config.lenses), **spec_kw).n_inputs
    _check_memory(config)
    for li, lens in enumerate(lens_objs):
        k0 = config.kernel_size or PAPER_KERNEL
        say(f"{lens.id}: PSF library ({config.n_fields} fields x {config.n_depths + 1} depth bins"
            + (f" x {config.focus_bins} focus bins" if lens.id in config.focus_lenses else "") + f", {k0} px)")
        libs, k_lib = _open_libraries(lens, config, k0, cache_dir, progress, say)
        psf_all = np.concatenate([l.psf.reshape(-1, 3, k_lib, k_lib) for l in libs])
        outside = np.concatenate([l.energy_outside.reshape(-1, 3) for l in libs])
        zero = np.concatenate([l.zero_energy.ravel() for l in libs])
        if config.variant == "radial" and config.kernel_size is None:
            k, held = energy_kernel_size(psf_all[~zero], outside[~zero], config.energy)
            if held < config.energy - 1e-9:
                warnings.warn(f"{lens.id}: a {k} x {k} kernel (the most allowed, max_kernel) holds only "
                              f"{held:.1%} of some PSFs' energy", KernelTooSmallWarning, stacklevel=2)
        else:
            k = k_lib
            held = float((1.0 - outside[~zero]).min()) if (~zero).any() else 1.0
        ls = LensSamples(lens, li, k, libs, config.focus_values_m(lens.id), libs[0].pixel_pitch_mm, held)
        settings = config.psf_settings(k_lib)
        if config.variant == "radial":
            nf, nd = config.n_fields, config.n_depths + 1
            fields = np.broadcast_to(libs[0].fields[None, None, :], (len(libs), nd, nf))
            dio = np.broadcast_to(libs[0].diopters[None, :, None], (len(libs), nd, nf))
            fv = focus_diopters(lens, [np.nan if f is None else f for f in ls.focus_values_m])
            fdio = np.broadcast_to(fv[:, None, None], (len(libs), nd, nf))
            x = encode_radial(spec_d, li, fields, dio, fdio if focus and lens.id in config.focus_lenses else None)
            ls.grid_x = x[~zero].astype(np.float32)
            ls.grid_y = crop_normalise(psf_all[~zero], k)
        else:
            ls.geometry = ImageGeometry.full_sensor(lens, PAPER_GRID["height"], PAPER_GRID["width"])
        # traced points: off-grid training and held-out
        for which, n, tag in (("off", config.offgrid, 1), ("val", config.held_out, 2)):
            name = f"{lens.id}.{which}"
            if stored is not None and name + ".x" in stored:
                setattr(ls, which + "_x", stored[name + ".x"])
                setattr(ls, which + "_y", stored[name + ".y"])
                if which == "val":
                    ls.val_coords = {c: stored[f"{name}.{c}"] for c in ("field", "depth_m", "focus_m", "row", "col")
                                     if f"{name}.{c}" in stored}
                continue
            rng = np.random.default_rng([config.seed, li, tag])
            if n == 0:
                setattr(ls, which + "_x", np.zeros((0, n_inputs), np.float32))
                setattr(ls, which + "_y", np.zeros((0, 3, k, k), np.float32))
                continue
            rm = config.raymap(lens) if which == "off" else None      # held-out points: always traced
            rays = settings if which == "off" or config.held_out_rays is None else \
                replace(settings, pupil_samples=config.held_out_rays)
            say(f"{lens.id}: {'tracing' if rm is None else 'depositing from its ray map'} {n} "
                f"{'off-grid training' if which == 'off' else 'held-out'} points ({rays.pupil_samples} rays a side)")
            if config.variant == "radial":
                f, d, fm = _draw_radial_points(rng, n, config, lens.id in config.focus_lenses)
                psf, ok = (trace_points(lens, rays, f, d, fm) if rm is None else
                           raymap_points(rm, lens, rays, f, d, fm))
                x = encode_radial(spec_d, li, f, inverse_depth(d, config.far_m),
                                  None if fm is None else focus_diopters(lens, fm))
                y = crop_normalise(psf, k)
                coords = {"field": f, "depth_m": d, "focus_m": fm}
            else:
                rows, cols, d = _draw_paper_points(rng, n, config)
                pr, pc = patch_centres_px(spec_d, rows, cols)
                f = np.minimum(ls.geometry.field(pr, pc), 1.0)
                psf, ok = trace_points(lens, rays, f, d) if rm is None else raymap_points(rm, lens, rays, f, d)
                y = peak_normalise(rotate_exact(crop_normalise(psf, k), _outward(ls.geometry, pr, pc)))
                x = encode_paper(spec_d, li, rows, cols, d)
                coords = {"field": f, "depth_m": d, "row": rows, "col": cols}
            setattr(ls, which + "_x", x[ok].astype(np.float32))
            setattr(ls, which + "_y", y[ok])
            if which == "val":
                ls.val_coords = {c: np.asarray(v)[ok] for c, v in coords.items() if v is not None}
        out.append(ls)
    spec_kw["kernel_sizes"] = tuple(ls.kernel_size for ls in out)
    data = OLFData(config, out, spec_kw)
    if points_file and stored is None:
        _write_points(points_file, key, data)
    return data


def _outward(geometry: ImageGeometry, rows_px, cols_px) -> np.ndarray:
    vec = np.stack([np.asarray(rows_px) - geometry.center_px[0], np.asarray(cols_px) - geometry.center_px[1]], -1)
    norm = np.hypot(vec[:, 0], vec[:, 1])
    return np.where(norm[:, None] > 1e-9, vec / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])


def rotate_exact(kernels: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """``rotate_radial_kernels`` computed over each kernel's support only (the
    square about the centre that holds the disk of every nonzero pixel, plus
    two pixels, beyond which bilinear taps of a rotation read only zeros):
    the same result, at the cost of a small kernel's support, not k x k."""
    n, c, k, _ = kernels.shape
    r = k // 2
    half = np.minimum(support_radius(kernels, 0.0) + 2, r)
    out = np.zeros_like(kernels, dtype=np.float32)
    for h in np.unique(half):
        sel = np.nonzero(half == h)[0]
        sl = slice(r - h, r + h + 1)
        out[sel, :, sl, sl] = rotate_radial_kernels(kernels[sel][:, :, sl, sl], outward[sel])
    return out


def paper_targets_from_library(ls: LensSamples, rows, cols, depths) -> np.ndarray:
    """Peak-normalised 2-D PSFs (n, 3, k, k) of paper-grid patches (rows, cols)
    at ``depths``, from the lens's library (interpolated and rotated)."""
    spec_d = {"paper_grid": PAPER_GRID}
    pr, pc = patch_centres_px(spec_d, rows, cols)
    f = np.minimum(ls.geometry.field(pr, pc), 1.0)
    lib = ls.libraries[0]
    radial = lib.at(f, np.asarray(depths, float))
    if radial.shape[-1] != ls.kernel_size:
        radial = crop_normalise(radial, ls.kernel_size)
    return peak_normalise(rotate_exact(radial, _outward(ls.geometry, pr, pc)))


def _read_points(path, key):
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            return {k: z[k] for k in z.files if k != "key"}
    except (OSError, ValueError, KeyError):
        return None


def _write_points(path, key, data: OLFData):
    arrays = {"key": np.array(key)}
    for ls in data.lenses:
        for which in ("off", "val"):
            arrays[f"{ls.lens.id}.{which}.x"] = getattr(ls, which + "_x")
            arrays[f"{ls.lens.id}.{which}.y"] = getattr(ls, which + "_y")
        for c, v in ls.val_coords.items():
            arrays[f"{ls.lens.id}.val.{c}"] = np.asarray(v, np.float64)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            from ...io.npzfile import save_npz
            save_npz(f, arrays, compressed=False)
