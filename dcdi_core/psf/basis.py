"""A PSF library stored compactly: a low-rank basis of its kernels and their coefficients.

Per colour channel c, the kernels of a traced library over its grid (depth
bins x fields, N kernels of k x k pixels) are the rows of X_c (N, k^2); the
truncated SVD gives an orthonormal basis B_c (r, k^2) and coefficients
C_c = X_c B_c^T (N, r), so X_c ~ C_c B_c. The file holds B_c (float16; its
left half and centre column: a radial kernel is mirror-symmetric across the
radial axis, exactly, so is every basis vector) and C_c (float16) instead of
X_c: 1-5 MB per lens instead of 7-70 MB.

Serving is linear: the kernel at a grid point is C_c[n] B_c, so interpolating
coefficients (linear in field and inverse depth, ``PSFLibrary.at``) is
interpolating kernels, exactly as the traced library does. A truncated
basis leaves a small ripple: each served kernel is clipped at zero (and below
its ripple floor, a fraction of its peak) and each channel renormalised to sum 1 (a
kernel with no energy stays zero).

Truncation drops ray noise as well as detail: the kernels are pixel
histograms of a finite ray fan, their noise spreads over all k^2 directions
while the signal lives in a few, so the rank-r kernels are closer to the
converged PSFs than the kernels they were made from (measured by `dcdi
report psf-source` against kernels traced with 16 x the rays).

:class:`BasisLibrary` serves a store through the traced library's
interface (``grid``, ``depth_bins``, ``field_weights``, ``ensure``, ``psf``,
``computed``, ``kernel_size``, ``pixel_pitch_mm``, ``settings``), so the
renderer takes it unchanged; at a pixel pitch coarser than the stored one its
kernels are area-resampled (``psf.pitch``); a finer pitch is refused. Only
the lens whose optical fingerprint the store was built from is served, at
its prescribed focus.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..io.npzfile import (FileCache, Record, check_array, check_declared_bytes, file_error_text, read_format,
                          write_format)
from ..errors import InputRangeError, field
from ..optics.errors import OpticsError
from .compute import PSFSettings
from .library import LibraryGrid, PSFLibrary
from ..optics.lens import lens_fingerprint
from ..shipped import BASIS_DIR, basis_file
from .pitch import area_resample, check_downsampling, resampled_size, same_pitch

FORMAT = "dcdi-psf-basis"
FORMAT_VERSION = 1
MAX_FOCUS_SLICES = 64                   # focus distances of a focus stack
STORE_DIR = BASIS_DIR                   # the shipped stores (``shipped.BASIS_DIR``)


class BasisFileError(OpticsError):
    """A PSF basis file that cannot be used (damaged, another format or version)."""


@dataclass(frozen=True)
class BasisRecipe:
    """How a lens's store is built: the traced library's settings (rays per
    pupil side, grid, pixel pitch as a multiple of the sensor's, kernel size)
    and the rank kept per channel."""

    rays: int = 256
    n_fields: int = 64
    n_depths: int = 40
    pitch_factor: int = 1
    kernel_size: int = 41
    rank: int = 64
    near_m: float = 0.7
    far_m: float = 10.0
    ripple_floor: float = 3e-4
    near_rays: int | None = None        # more rays for the bins at or nearer than near_until_m
    near_until_m: float = 1.0
    focus_slices: int | None = None     # a focus stack: this many focus distances, uniform in 1/focus
    focus_near_m: float = 0.7           # ... from infinity to this distance

    def focus_diopters(self) -> np.ndarray | None:
        """The stack's focus distances as diopters (1/m), increasing from 0
        (infinity) to 1 / ``focus_near_m``; None for a store at the prescribed focus."""
        if self.focus_slices is None:
            return None
        return np.linspace(0.0, 1.0 / self.focus_near_m, self.focus_slices)

    FLAGS = {"rays": "--rays", "n_fields": "--fields", "n_depths": "--depths", "pitch_factor": "--pitch-factor",
             "rank": "--rank", "kernel_size": "--kernel"}

    def __post_init__(self):
        for name in ("rays", "n_fields", "n_depths", "pitch_factor", "rank"):
            if getattr(self, name) < 1:
                raise InputRangeError(f"{name} ({self.FLAGS[name]})", getattr(self, name), ">= 1")
        if self.n_fields < 2 or self.n_depths < 2:
            raise InputRangeError(f"{field('n_fields')}, {field('n_depths')}", (self.n_fields, self.n_depths), ">= 2")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise InputRangeError("kernel_size", self.kernel_size, "odd integer >= 1")
        if self.near_rays is not None and self.near_rays < 1:
            raise InputRangeError("near_rays", self.near_rays, ">= 1, or None")
        if not (self.near_m <= self.near_until_m < self.far_m):
            raise InputRangeError("near_until_m", self.near_until_m, f"[{self.near_m}, {self.far_m}) m")
        if not (0.0 <= self.ripple_floor < 0.1):
            raise InputRangeError("ripple_floor", self.ripple_floor, "[0, 0.1) of a kernel's peak")
        if self.focus_slices is not None and not 2 <= self.focus_slices <= MAX_FOCUS_SLICES:
            raise InputRangeError("focus_slices (--focus-slices)", self.focus_slices, f"[2, {MAX_FOCUS_SLICES}]")
        if not (0.0 < self.focus_near_m < math.inf):
            raise InputRangeError("focus_near_m", self.focus_near_m, "> 0 and finite metres")

    @property
    def grid(self) -> LibraryGrid:
        return LibraryGrid(n_fields=self.n_fields, n_depths=self.n_depths, near_m=self.near_m, far_m=self.far_m)

    def near_bins(self) -> np.ndarray:
        """The depth bins at or nearer than ``near_until_m`` (traced with ``near_rays``)."""
        return np.flatnonzero(self.grid.diopters >= 1.0 / self.near_until_m - 1e-9)

    def settings(self, lens) -> PSFSettings:
        """The traced library's PSF settings (the shipped band, wavelengths and
        deposit; the prescribed focus)."""
        from .compute import pixel_pitch_mm
        base = PSFSettings(kernel_size=self.kernel_size, pupil_samples=self.rays)
        return replace(base, pixel_pitch_mm=pixel_pitch_mm(lens, base) * self.pitch_factor)


# The shipped stores (`dcdi psflib compress --recipe shipped`): ranks, grids and
# rays chosen by `python -m lab report psf-source` (docs/psf.md, "Compact PSF sources").
# The 6P and the double Gauss trace their bins nearer than 1 m with 512 rays:
# there a 256-ray kernel's own ray noise (38 dB against 1024 rays) was the
# worst point's error. The double Gauss keeps its faint halo (a ripple floor cut it: relative L1
# 0.0168 -> 0.0215). It is stored at 3 x its sensor pitch (0.46 um; its sensor's
# 0.154 um is far below its 1.3 um Airy disk, and its near blur spans
# 230 px there).
SHIPPED_RECIPES = {
    "mos-s1": BasisRecipe(kernel_size=41, rank=48),
    "mos-s2": BasisRecipe(kernel_size=47, rank=48),
    "6p": BasisRecipe(kernel_size=71, n_depths=64, rank=160, near_rays=512),
    "double-gauss": BasisRecipe(kernel_size=77, n_fields=32, n_depths=96, rank=168, pitch_factor=3,
                                ripple_floor=0.0, near_rays=512),
}


# The shipped focus stacks (`dcdi psflib compress LENS --focus-slices 6`): the
# lenses the OLF did not learn across focus (the singlets refocus by moving
# the sensor). Six focus distances uniform in 1/focus from infinity to 0.7 m;
# between two, `BasisStore.at_focus` matches each depth's defocus exactly and
# interpolates only what else changes with the focus, so that few slices do
# (`python -m lab focus-stack`: its error against tracing and its time, docs/psf.md).
SHIPPED_FOCUS_RECIPES = {
    "mos-s1": BasisRecipe(kernel_size=41, n_fields=32, rank=48, rays=128, focus_slices=6),
    "mos-s2": BasisRecipe(kernel_size=47, n_fields=32, rank=48, rays=128, focus_slices=6),
}


def shipped_store(lens_id: str, focus_stack: bool = False) -> Path | None:
    """The shipped store file of a lens (its focus stack with ``focus_stack``),
    or None (``shipped.basis_file``)."""
    return basis_file(lens_id, focus_stack)


# ----------------------------------------------------------------- building
def factorise(kernels: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernels (N, 3, k, k) -> basis (3, r, k^2) with orthonormal rows and
    coefficients (N, 3, r), r = min(rank, N, k^2), by the truncated SVD."""
    n, c, k, _ = kernels.shape
    r = min(rank, n, k * k)
    basis = np.zeros((c, r, k * k))
    coeffs = np.zeros((n, c, r))
    for ch in range(c):
        x = kernels[:, ch].reshape(n, k * k).astype(np.float64)
        _, _, vt = np.linalg.svd(x, full_matrices=False)
        basis[ch] = vt[:r]
        coeffs[:, ch] = x @ vt[:r].T
    return basis, coeffs


# Below this fraction of a channel's peak a reconstructed value is the
# truncation's ripple, not the PSF: zeroed (the default of a recipe, stored
# in the file; measured on the 6P at rank 160: kernels' 99.9 % support back
# from 29 to 26 px median, the library's 25, so its PSF map costs 0.84 s
# instead of 1.32 s; off-grid PSNR unchanged, relative L1 0.0217 -> 0.0192;
# 1e-3 starts to cut real halo)
RIPPLE_FLOOR = 3e-4


def reconstruct(coeffs: np.ndarray, basis: np.ndarray, k: int | None = None,
                floor: float = RIPPLE_FLOOR) -> np.ndarray:
    """Kernels (..., 3, k, k) from coefficients (..., 3, r) and a basis
    (3, r, k^2), or (``k`` given) its left half and centre column (3, r,
    k (k // 2 + 1)) of a mirror-symmetric basis (half the products): clipped
    at zero, values below ``floor`` of the channel's peak zeroed, each
    channel summing to 1 (0 if it holds no energy)."""
    c, r, cols = basis.shape
    half = k is not None
    k = k if half else math.isqrt(cols)
    lead = coeffs.shape[:-2]
    flat = coeffs.reshape(-1, c, r)
    out = np.empty((len(flat), c, cols), np.result_type(coeffs, basis))
    for ch in range(c):                 # one matrix product per channel (BLAS)
        np.matmul(flat[:, ch], basis[ch], out=out[:, ch])
    if not half:
        out[out < floor * out.max(axis=-1, keepdims=True)] = 0.0     # negative lobes included
        s = out.sum(axis=-1, keepdims=True)
        return np.divide(out, s, out=np.zeros_like(out), where=s > 0).reshape(lead + (c, k, k))
    # on the left half (the right one is its mirror): the peak is the half's,
    # the sum twice the half's less the centre column
    h = k // 2 + 1
    left = out.reshape(len(flat), c, k, h)
    peak = left.max(axis=(-1, -2), keepdims=True)
    left[left < floor * peak] = 0.0
    s = 2.0 * left.sum(axis=(-1, -2), keepdims=True) - left[..., -1:].sum(axis=-2, keepdims=True)
    np.divide(left, s, out=left, where=s > 0)      # s == 0: every value is already 0
    full = np.empty((len(flat), c, k, k), out.dtype)
    full[..., :h] = left
    full[..., h:] = left[..., -2::-1]
    return full.reshape(lead + (c, k, k))


@dataclass
class BasisStore:
    """One lens's kernels as basis + coefficients, and what they were built from.

    ``basis`` (3, r, k^2) and ``coeffs`` (D+1, F, 3, r), float16 as stored;
    ``zero_energy`` (D+1, F): grid points no ray reaches."""

    meta: dict
    basis: np.ndarray
    coeffs: np.ndarray
    zero_energy: np.ndarray
    path: str = "<memory>"

    ARRAYS = ("basis_half", "coeffs", "zero_energy")

    @property
    def lens_id(self) -> str:
        return self.meta["lens_id"]

    @property
    def grid(self) -> LibraryGrid:
        return LibraryGrid(**self.meta["grid"])

    @property
    def settings(self) -> PSFSettings:
        s = dict(self.meta["psf_settings"])
        s["band_nm"] = tuple(s["band_nm"])
        return PSFSettings(**s)

    @property
    def pixel_pitch_mm(self) -> float:
        return float(self.meta["pixel_pitch_mm"])

    @property
    def kernel_size(self) -> int:
        return int(self.meta["kernel_size"])

    @property
    def rank(self) -> int:
        return int(self.basis.shape[1])

    @property
    def focus_diopters(self) -> np.ndarray | None:
        """A focus stack's focus distances (1/m, increasing; 0 is infinity), None for one focus."""
        fd = self.meta.get("focus_diopters")
        return None if fd is None else np.asarray(fd, float)

    def focus_range_m(self) -> tuple[float, float]:
        """A focus stack's (nearest, farthest) focus distance, metres (inf where it reaches infinity)."""
        fd = self.focus_diopters
        return 1.0 / fd[-1], (math.inf if fd[0] == 0 else 1.0 / fd[0])

    def covers_focus(self, focus_m) -> bool:
        fd = self.focus_diopters
        d = _diopters(focus_m)
        return fd is not None and d is not None and fd[0] - 1e-12 <= d <= fd[-1] + 1e-12

    def at_focus(self, focus_m, *, match_defocus: bool = True) -> "BasisStore":
        """The one-focus store a focus stack gives at ``focus_m`` (metres, or
        inf), within its range.

        Between the stored focus distances a and b about it (diopters f_a <=
        f <= f_b, t = (f - f_a) / (f_b - f_a)), a depth bin at g diopters
        gets (1 - t) C_a(g - f + f_a) + t C_b(g - f + f_b), C_s(x) being
        focus s's coefficients linear in diopters along its depth bins: the
        bin's thin-lens defocus (g - f) is each term's own, so that only what
        else changes with the focus (the magnification, the aberrations) is
        interpolated. Where a shifted depth falls outside the depth bins
        (beyond infinity, nearer than the nearest bin), the other focus
        serves alone. Coefficients are linear in the kernels, so this is
        interpolating kernels. ``match_defocus`` False: each bin's kernels
        at the two focus distances interpolated as they are (what the depth
        shift improves on: ``python -m lab focus-stack``)."""
        fd = self.focus_diopters
        if fd is None:
            raise InputRangeError("focus stack", self.path, "a focus-stack PSF basis (this one holds one focus)")
        if not self.covers_focus(focus_m):
            near, far = self.focus_range_m()
            raise InputRangeError("focus_m", focus_m, f"{near:.3g} m to {far:.3g} m (the focus stack {self.path})")
        f = min(max(_diopters(focus_m), fd[0]), fd[-1])
        a = int(np.clip(np.searchsorted(fd, f, side="right") - 1, 0, len(fd) - 2))
        t = (f - fd[a]) / (fd[a + 1] - fd[a])
        g = self.grid.diopters
        xa, xb = (g - f + fd[a], g - f + fd[a + 1]) if match_defocus else (g, g)
        lo, hi = g.min() - 1e-9, g.max() + 1e-9
        ina, inb = (xa >= lo) & (xa <= hi), (xb >= lo) & (xb <= hi)
        wb = np.where(ina & inb, t, np.where(ina, 0.0, 1.0))
        coeffs = ((1.0 - wb)[:, None, None, None] * _along_depth(self.coeffs[a], g, xa)
                  + wb[:, None, None, None] * _along_depth(self.coeffs[a + 1], g, xb)).astype(np.float32)
        meta = {key: v for key, v in self.meta.items() if key != "focus_diopters"}
        meta["psf_settings"] = dict(meta["psf_settings"], focus_distance_m=float(focus_m))
        meta["checksum"] = f"{self.meta.get('checksum')}@{float(focus_m):.9g}"
        meta["focus_from_stack"] = {"focus_diopters": [float(fd[a]), float(fd[a + 1])], "t": float(t)}
        return BasisStore(meta, self.basis, coeffs, ~np.any(coeffs != 0, axis=(-1, -2)), self.path)

    def kernels_at_bins(self, bins, dtype=np.float32) -> np.ndarray:
        """Kernels (len(bins), F, 3, k, k) of whole depth bins (every field)."""
        b, k = self._cast(dtype)
        floor = float(self.meta.get("ripple_floor", RIPPLE_FLOOR))
        return reconstruct(self.coeffs[np.asarray(bins, int)].astype(dtype), b, k, floor).astype(np.float32,
                                                                                                  copy=False)

    def _cast(self, dtype):
        """(basis in ``dtype``, k): its left half when mirror-symmetric (k given), else whole (k None)."""
        cache = self.__dict__.setdefault("_basis_cast", {})
        key = np.dtype(dtype).str
        if key not in cache:
            c, r, kk = self.basis.shape
            k = math.isqrt(kk)
            if mirror_symmetric(self.basis):
                half = self.basis.reshape(c, r, k, k)[..., :k // 2 + 1].reshape(c, r, -1)
                cache[key] = (np.ascontiguousarray(half, dtype=dtype), k)
            else:
                cache[key] = (self.basis.astype(dtype), None)
        return cache[key]

    def check_lens(self, lens) -> None:
        """Refuses a lens whose prescription is not the one the store was built from."""
        fp = lens_fingerprint(lens)
        if lens.id != self.lens_id or fp != self.meta["lens_fingerprint"]:
            raise OpticsError(f"{self.path}: built for {self.lens_id} ({self.meta.get('lens_file')}; fingerprint "
                              f"{self.meta['lens_fingerprint'][:12]}...), not {lens.id} ({lens.path}; {fp[:12]}...): "
                              "trace its PSFs instead")

    # ---------------------------------------------------------- storage
    def file_arrays(self, dtype=np.float16) -> dict:
        """The arrays as the file holds them: the basis's left half and centre
        column only (a radial kernel is mirror-symmetric across its radial
        axis, ``mirror_symmetric``), basis and coefficients in ``dtype``."""
        c, r, kk = self.basis.shape
        k = math.isqrt(kk)
        return {"basis_half": self.basis.reshape(c, r, k, k)[..., :k // 2 + 1].astype(dtype),
                "coeffs": self.coeffs.astype(dtype), "zero_energy": self.zero_energy.astype(bool)}

    def save(self, path) -> None:
        if not mirror_symmetric(self.basis):
            raise InputRangeError("basis", "not mirror-symmetric across the radial axis",
                                  "a radial library's kernels (rows along the radius)")
        write_format(path, self.meta, self.file_arrays(), FORMAT, FORMAT_VERSION)

    @classmethod
    def load(cls, path) -> "BasisStore":
        """A store file, read by the shared checked reader (``io.npzfile``:
        size limits, array headers before data, no pickle, finite values),
        its format, version and checksum, then every field (:func:`check_store`)
        before the basis is expanded."""
        path = Path(path)
        fail = basis_fail(path)
        meta, arrays = read_format(path, fail, FORMAT, FORMAT_VERSION)
        check_store(meta, arrays, fail)
        half, coeffs = arrays["basis_half"].astype(np.float32), arrays["coeffs"].astype(np.float32)
        k = int(meta["kernel_size"])
        basis = np.concatenate([half, half[..., -2::-1]], axis=-1).reshape(half.shape[0], half.shape[1], k * k)
        return cls(meta, basis, coeffs, arrays["zero_energy"], str(path))


def _diopters(focus_m) -> float | None:
    """1 / ``focus_m`` (0 for infinity); None for anything not a positive distance."""
    try:
        f = float(focus_m)
    except (TypeError, ValueError):
        return None
    return None if not f > 0 else (0.0 if math.isinf(f) else 1.0 / f)


def _along_depth(coeffs: np.ndarray, g: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``coeffs`` (D+1, ...) given at depth bins of diopters ``g`` (decreasing)
    at diopters ``x`` (D+1,), linear in diopters, clamped to the bins' range."""
    gs = g[::-1]                                    # increasing
    xs = np.clip(x, gs[0], gs[-1])
    i = np.clip(np.searchsorted(gs, xs, side="right") - 1, 0, len(gs) - 2)
    w = ((xs - gs[i]) / (gs[i + 1] - gs[i])).reshape((-1,) + (1,) * (coeffs.ndim - 1))
    c = coeffs[::-1]
    return (1.0 - w) * c[i] + w * c[i + 1]


# ----------------------------------------------------------------- loading
# the limits of a store's metadata, checked on load (the shipped: k 41-77,
# rank 48-168, grids of 32-64 fields by 40-96 depths)
MAX_KERNEL = 255                 # px, odd
MAX_GRID = 1024                  # fields, depth bins


def basis_fail(path):
    """``fail(message, field=None, allowed=None)`` of ``io.npzfile`` for a store: a BasisFileError."""
    return lambda message, field=None, allowed=None: BasisFileError(file_error_text(path, message, field, allowed))


def check_store(meta: dict, arrays: dict, fail) -> None:
    """Every field of a store's metadata that serving reads, in its range,
    and its arrays shaped as its grid, rank and kernel size say."""
    rec = Record(meta, fail)
    rec.name("lens_id")
    rec.text("lens_fingerprint", max_chars=128)
    k = rec.integer("kernel_size", 1, MAX_KERNEL, odd=True)
    rank = rec.integer("rank", 1, k * k)
    rec.number("pixel_pitch_mm", 0.0, 10.0, lo_open=True)
    rec.number("ripple_floor", 0.0, 0.1, optional=True)
    grid = check_grid(rec.sub("grid"), k, fail)
    check_psf_settings(rec.sub("psf_settings"), fail)
    rows = (grid["n_depths"] + 1, grid["n_fields"])
    if meta.get("focus_diopters") is not None:         # a focus stack: one set of coefficients per focus
        fd = rec.numbers("focus_diopters", 0.0, 1e3, (2, MAX_FOCUS_SLICES))
        if np.any(np.diff(np.asarray(fd, float)) <= 0):
            raise fail("focus_diopters not increasing", field="focus_diopters",
                       allowed=f"2-{MAX_FOCUS_SLICES} increasing diopters (1/focus distance, 0 = infinity)")
        rows = (len(fd),) + rows
    check_array(arrays, "basis_half", (3, rank, k, k // 2 + 1), fail)
    check_array(arrays, "coeffs", rows + (3, rank), fail)
    check_array(arrays, "zero_energy", rows, fail, kinds="b")


def check_grid(rec: Record, kernel_size: int, fail) -> dict:
    """A recorded ``LibraryGrid`` (its fields, ranges and order), and the PSF
    library it sizes at ``kernel_size`` px within ``io.npzfile.MAX_DECLARED_BYTES``."""
    rec.allowed_keys(("n_fields", "n_depths", "near_m", "far_m"))
    out = {"n_fields": rec.integer("n_fields", 2, MAX_GRID), "n_depths": rec.integer("n_depths", 2, MAX_GRID),
           "near_m": rec.number("near_m", 0.0, 1e6, lo_open=True, optional=True),
           "far_m": rec.number("far_m", 0.0, 1e6, lo_open=True, optional=True)}
    try:
        LibraryGrid(**{key: v for key, v in out.items() if v is not None})
    except InputRangeError as e:
        raise fail(str(e), field=rec.where("near_m"), allowed="0 < near_m < far_m") from None
    library = (out["n_depths"] + 1) * out["n_fields"] * 3 * kernel_size * kernel_size * 4
    check_declared_bytes(library, f"the PSF library of this grid at {kernel_size} px", rec.prefix.rstrip("."),
                         fail)
    return out


def check_psf_settings(rec: Record, fail) -> PSFSettings:
    """Recorded ``PSFSettings``: only its fields, each of its type and range."""
    from dataclasses import fields
    rec.allowed_keys([f.name for f in fields(PSFSettings)])
    rec.integer("kernel_size", 1, 4095, odd=True, optional=True)
    rec.integer("pupil_samples", 1, 1 << 16, optional=True)
    rec.integer("n_wavelengths", 1, 4096, optional=True)
    rec.integer("oversample", 1, 1024, optional=True)
    rec.numbers("band_nm", 300.0, 1100.0, (2, 2), optional=True)
    rec.choice("precision", ("float64", "float32"), optional=True)
    rec.number("deposit_sigma_px", 0.0, 3.0, optional=True)
    rec.number("wavelength_nm", 200.0, 2500.0, optional=True)
    rec.number("pixel_pitch_mm", 0.0, 10.0, lo_open=True, optional=True)
    rec.number("focus_distance_m", 0.0, 1e6, lo_open=True, inf=True, optional=True)
    settings = dict(rec.table)
    if settings.get("band_nm") is not None:
        settings["band_nm"] = tuple(settings["band_nm"])
    try:
        return PSFSettings(**settings)
    except InputRangeError as e:
        raise fail(str(e), field=rec.prefix.rstrip(".")) from None


def mirror_symmetric(basis: np.ndarray, tol: float = 1e-4) -> bool:
    """True if every basis vector (3, r, k^2) is symmetric under a flip of the
    kernel's columns (x -> -x across the radial axis): a rotationally
    symmetric lens's PSF is, and the tracer's pupil grid keeps it so."""
    c, r, kk = basis.shape
    k = math.isqrt(kk)
    b = basis.reshape(c, r, k, k)
    return bool(np.abs(b - b[..., ::-1]).max() <= tol * max(np.abs(b).max(), 1e-30))


def _cropped(library: PSFLibrary, kernel_size: int | None):
    """(kernels (D+1, F, 3, k, k) float64 cropped to ``kernel_size`` and each
    channel renormalised, the energy each crop holds of the arriving energy, k)."""
    if not library.computed.all():
        raise InputRangeError("library", f"{int(library.computed.sum())} of {len(library.computed)} depth bins",
                              "every depth bin computed (build it first)")
    k = kernel_size or library.kernel_size
    if k > library.kernel_size or k % 2 == 0:
        raise InputRangeError("kernel_size", k, f"odd, <= the library's {library.kernel_size}")
    psf = library.psf.astype(np.float64)
    r0, h = library.kernel_size // 2, k // 2
    crop = psf[..., r0 - h:r0 + h + 1, r0 - h:r0 + h + 1]
    held = crop.sum(axis=(-1, -2)) * (1.0 - library.energy_outside)        # of the arriving energy
    s = crop.sum(axis=(-1, -2), keepdims=True)
    return np.divide(crop, s, out=np.zeros_like(crop), where=s > 0), held, k


def _store_meta(library: PSFLibrary, k: int, rank: int, held: np.ndarray, live: np.ndarray, build_s: float,
                ripple_floor: float) -> dict:
    return {"lens_id": library.meta["lens_id"], "lens_file": library.meta["lens_file"],
            "lens_fingerprint": library.meta["lens_fingerprint"],
            "psf_settings": replace(library.settings, kernel_size=k).as_dict(),
            "grid": asdict(library.grid), "pixel_pitch_mm": library.pixel_pitch_mm, "kernel_size": k,
            "rank": int(rank), "response_sha256": library.meta["response"]["sha256"],
            "psf_algorithm": library.meta["algorithm"],
            "energy_held_min": float(held[live].min()) if live.any() else 1.0,
            "build_s": float(build_s), "ripple_floor": float(ripple_floor)}


def compress(library: PSFLibrary, rank: int, *, kernel_size: int | None = None, build_s: float = 0.0,
             ripple_floor: float = RIPPLE_FLOOR) -> BasisStore:
    """The store of a fully computed traced library: its kernels (centred
    ``kernel_size`` crop, renormalised, if given) factorised to ``rank`` per
    channel."""
    crop, held, k = _cropped(library, kernel_size)
    d, f = crop.shape[:2]
    basis, coeffs = factorise(crop.reshape(d * f, 3, k, k), rank)
    meta = _store_meta(library, k, basis.shape[1], held, ~library.zero_energy, build_s, ripple_floor)
    return BasisStore(meta, basis.astype(np.float32), coeffs.reshape(d, f, 3, -1).astype(np.float32),
                      library.zero_energy.copy())


def compress_stack(libraries: list, focus_diopters, rank: int, *, kernel_size: int | None = None,
                   build_s: float = 0.0, ripple_floor: float = RIPPLE_FLOOR) -> BasisStore:
    """A focus stack: the libraries of one lens and grid traced at
    ``focus_diopters`` (1/m, increasing; one library each), factorised
    together (one basis, coefficients per focus)."""
    fd = np.asarray(focus_diopters, float)
    if len(libraries) != len(fd) or len(fd) < 2 or np.any(np.diff(fd) <= 0):
        raise InputRangeError("focus_diopters", fd.tolist(), "increasing, one per library, at least 2")
    if len({(lib.meta["lens_fingerprint"], lib.grid) for lib in libraries}) != 1:
        raise InputRangeError("libraries", "of different lenses or grids", "one lens, one grid")
    crops = [_cropped(lib, kernel_size) for lib in libraries]
    k = crops[0][2]
    stack = np.stack([c[0] for c in crops])                        # (S, D+1, F, 3, k, k)
    n_s, d, f = stack.shape[:3]
    basis, coeffs = factorise(stack.reshape(n_s * d * f, 3, k, k), rank)
    zero = np.stack([lib.zero_energy for lib in libraries])
    held = np.stack([c[1] for c in crops])
    meta = _store_meta(libraries[0], k, basis.shape[1], held, ~zero, build_s, ripple_floor)
    meta["psf_settings"]["focus_distance_m"] = None
    meta["focus_diopters"] = [float(x) for x in fd]
    return BasisStore(meta, basis.astype(np.float32), coeffs.reshape(n_s, d, f, 3, -1).astype(np.float32), zero)


def traced_library(lens, recipe: BasisRecipe, *, cache_dir=None, progress=None, log=None,
                   focus_m: float | None = None) -> tuple:
    """(the fully computed traced library ``recipe`` describes, seconds traced
    now: 0 if it all came from the PSF cache). ``cache_dir`` None: the
    default cache, False: none. With ``near_rays``, the bins at or nearer
    than ``near_until_m`` come from a second library traced with that many
    rays (the same grid and settings otherwise). ``focus_m``: refocused
    there (metres, inf; None: as prescribed)."""
    import warnings
    from .compute import KernelTooSmallWarning
    seconds = 0.0

    def trace(settings, bins):
        nonlocal seconds
        lib = PSFLibrary.open(lens, settings, recipe.grid, cache=cache_dir is not False, cache_dir=cache_dir or None)
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            done = lib.ensure(bins=bins, progress=progress)
        seconds += (time.perf_counter() - t) if done else 0.0
        if log:
            log(f"{lens.id}: {len(bins)} depth bins x {len(lib.fields)} fields at {settings.pupil_samples} rays"
                + ("" if focus_m is None else f", focus {focus_m:.4g} m") + " "
                + (f"traced in {time.perf_counter() - t:.0f} s" if done else "from the cache"))
        return lib

    settings = replace(recipe.settings(lens), focus_distance_m=focus_m)
    lib = trace(settings, np.arange(len(recipe.grid.depths_m)))
    if recipe.near_rays:
        near = recipe.near_bins()
        fine = trace(replace(settings, pupil_samples=recipe.near_rays), near)
        for name in PSFLibrary.ARRAYS:
            getattr(lib, name)[near] = getattr(fine, name)[near]
    return lib, seconds


def build_store(lens, recipe: BasisRecipe, *, cache_dir=None, progress=None, log=None) -> BasisStore:
    """Trace ``lens``'s library as ``recipe`` says (:func:`traced_library`;
    one per focus distance of a focus stack) and compress it."""
    fd = recipe.focus_diopters()
    if fd is not None:
        libs, seconds = [], 0.0
        for d in fd:
            lib, s = traced_library(lens, recipe, cache_dir=cache_dir, progress=progress, log=log,
                                    focus_m=math.inf if d == 0 else 1.0 / d)
            libs.append(lib)
            seconds += s
        store = compress_stack(libs, fd, recipe.rank, build_s=seconds, ripple_floor=recipe.ripple_floor)
    else:
        lib, seconds = traced_library(lens, recipe, cache_dir=cache_dir, progress=progress, log=log)
        store = compress(lib, recipe.rank, build_s=seconds, ripple_floor=recipe.ripple_floor)
    store.meta["near_rays"] = recipe.near_rays
    store.meta["near_until_m"] = recipe.near_until_m if recipe.near_rays else None
    return store


# ----------------------------------------------------------------- serving
class BasisLibrary(PSFLibrary):
    """A PSF library of one lens whose bins are reconstructed from a
    :class:`BasisStore` (never traced), at the store's grid, at its pixel
    pitch or a coarser one (area-resampled); a focus stack's at ``focus_m``
    (:meth:`BasisStore.at_focus`)."""

    def __init__(self, store: BasisStore, lens, *, pixel_pitch_mm: float | None = None, focus_m=None):
        store.check_lens(lens)
        if store.focus_diopters is not None:        # a focus stack serves the focus given
            if focus_m is None:
                near, far = store.focus_range_m()
                raise InputRangeError("focus_m", None, f"a focus distance {near:.3g} m to {far:.3g} m "
                                                       f"(the focus stack {store.path})")
            store = store.at_focus(focus_m)
        elif focus_m is not None:
            raise InputRangeError("focus_m", focus_m, f"None: {store.path} holds {lens.id} at its prescribed focus")
        stored = store.pixel_pitch_mm
        pitch = stored if pixel_pitch_mm is None else float(pixel_pitch_mm)
        check_downsampling(stored, pitch, f"pixel pitch (mm; {store.path} holds {lens.id} at {stored:.6g} mm)")
        k = resampled_size(store.kernel_size, stored, pitch)
        settings = replace(store.settings, kernel_size=k, pixel_pitch_mm=pitch)
        self.store, self.stored_pitch_mm = store, stored
        self.last_reconstruct_s = 0.0
        grid = store.grid
        meta = {"format": "basis", "algorithm": store.meta.get("psf_algorithm"), "lens_id": lens.id,
                "lens_file": str(lens.path), "lens_fingerprint": store.meta["lens_fingerprint"],
                "settings": settings.as_dict(), "grid": asdict(grid), "pixel_pitch_mm": pitch,
                "wavelengths_nm": [], "response": {"sha256": "basis:" + str(store.meta.get("checksum"))},
                "basis_file": store.path}
        super().__init__(lens, settings, grid, None, meta=meta)
        self.zero_energy[...] = store.zero_energy

    @property
    def resampled(self) -> bool:
        return not same_pitch(self.pixel_pitch_mm, self.stored_pitch_mm)

    def kernels(self, field, depth_m) -> np.ndarray:
        """PSFs (..., 3, k, k) at fields x depths (broadcast), interpolated as
        the traced library's (``at``); a depth nearer than the grid's near
        limit is an error naming it."""
        return self.at(field, depth_m)

    def ensure(self, depth_m=None, *, bins=None, clamp_near: bool = False, progress=None) -> list[int]:
        want = np.asarray(bins if bins is not None else self.bins_needed(depth_m, clamp_near=clamp_near), int)
        todo = [int(b) for b in want if not self.computed[b]]
        if not todo:
            return []
        t = time.perf_counter()
        kernels = self.store.kernels_at_bins(todo)
        if self.resampled:
            kernels = area_resample(kernels, self.stored_pitch_mm, self.pixel_pitch_mm, self.kernel_size)
        self.psf[todo] = kernels
        self.computed[todo] = True
        self.energy_outside[todo] = 0.0
        self.kernel_size_needed[todo] = self.kernel_size
        self.last_reconstruct_s += time.perf_counter() - t
        if progress:
            progress(len(todo) * len(self.fields), len(todo) * len(self.fields))
        return todo

    def save(self, path) -> None:        # the store is the file
        raise OpticsError("a basis-backed library is not saved; it is computed from its basis file")


_STORES = FileCache(BasisStore.load, 8, "PSF bases")


def open_store(path) -> BasisStore:
    """``BasisStore.load``, kept for the next request of the same file (path,
    size, modification time): a new pixel pitch or a refocus opens a new
    library, not the file again."""
    try:
        return _STORES(path)
    except OSError as e:                # stat: missing or unreadable
        raise BasisFileError(f"{path}: not a readable PSF basis file ({type(e).__name__}: {e.strerror})") from None


__all__ = ["BasisLibrary", "BasisRecipe", "BasisStore", "BasisFileError", "SHIPPED_RECIPES",
           "SHIPPED_FOCUS_RECIPES", "build_store", "compress", "compress_stack", "factorise", "open_store", "reconstruct", "shipped_store", "STORE_DIR"]
