"""Ray maps: a lens's rays as polynomials of the stop, for PSFs at any focus,
f-number, iris and pixel pitch without tracing.

A traced PSF is the histogram of rays launched from one object point
through a grid of points on the stop (``compute``). For one object point
(field, depth) and one wavelength, where a ray lands on the sensor and
where it heads are smooth functions of where it crosses the stop, (u, v)
in units of the stop's prescribed radius: the lens's aberrations. A ray map
holds them as polynomials of (u, v), fitted by least squares to traced rays
on a grid of depths (uniform in diopters, infinity included) x fields x
wavelengths; likewise where the rays meet each surface that clips the beam
(mechanical vignetting), at the design wavelength. The lens being
symmetric about its meridional plane (the field along +y), x is odd in u and
y even.

A PSF is the polynomials evaluated at the stop grid the tracer would launch
(``aiming.stop_grid`` of the lens as asked), kept where every clipping
surface's clear aperture passes them, and deposited like traced rays
(``compute.rays_to_kernels``). So one file serves:

- any focus: the sensor moved by dz (``paraxial.refocused``) meets a ray at
  (x, y) + dz (dx/dz, dy/dz); the field is solved on the moved sensor;
- any f-number and iris: the stopped-down stop grid is a subset of (u, v)
  (radius N0 / N, the polygon of its blades);
- any pixel pitch, kernel size, ray count, wavelengths and spectral response
  (within the stored band): those are the deposit's.

Between grid points the coefficients are linear in field and in 1/depth;
between stored wavelengths the landing points are linear in wavelength.
What it costs against tracing is measured by ``python -m lab report
raymap`` (docs/psf.md).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from .. import caches
from ..errors import InputRangeError
from ..io.npzfile import FileCache, Record, check_array, file_error_text, read_format, write_format
from ..optics.aiming import aim_chief, pupil_rays, sources, stop_grid
from ..optics.errors import OpticsError
from ..optics.lens import Lens, lens_fingerprint
from ..optics.paraxial import image_distance_mm
from ..optics.trace import trace
from .compute import (KernelTooSmallWarning, PSFSettings, _illumination_geometry, clip_message, pixel_pitch_mm,
                      rays_to_kernels, spectral_samples)
from .library import LibraryGrid, PSFLibrary, _fitted

FORMAT = "dcdi-ray-map"
FORMAT_VERSION = 1
# a fitted ray reaches its stop target within this fraction of the stop's radius
AIM_TOLERANCE = 1e-4
# the reachable disc's radius beyond the farthest reachable target (a fraction of the stop's radius)
AIM_MARGIN = 1e-3
# centres tried for the reachable disc, on the meridional axis (stop radii)
AIM_CENTRES = np.linspace(-4.0, 4.0, 321)
# rays evaluated per batch of sources (bounds memory, ~60 bytes a ray and wavelength)
BATCH_RAYS = 1_500_000


class RayMapFileError(OpticsError):
    """A ray map file that cannot be used (damaged, another format or version)."""


@dataclass(frozen=True)
class RayMapRecipe:
    """How a ray map is built: its grid, its polynomials' degrees and the rays
    they are fitted to. Defaults from ``python -m lab report raymap``."""

    n_fields: int = 16              # fields uniform over [0, 1]
    n_depths: int = 16              # depth bins uniform in diopters from 1 / near_m to infinity (excluded)
    near_m: float = 0.4
    n_wavelengths: int = 7          # uniform over band_nm
    band_nm: tuple[float, float] = (400.0, 700.0)
    degree: int = 15                # landing point (x, y) on the sensor and on the near focus's sensor
    chroma_degree: int = 7          # its change from the middle wavelength to the others
    clip_degree: int = 9            # where a ray meets a clipping surface
    fit_samples: int = 96           # the fit's stop grid: fit_samples x fit_samples

    def __post_init__(self):
        for name, lo, hi in (("n_fields", 2, 256), ("n_depths", 1, 256), ("n_wavelengths", 2, 64),
                             ("degree", 1, 21), ("chroma_degree", 1, 21), ("clip_degree", 1, 21),
                             ("fit_samples", 8, 1024)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise InputRangeError(name, v, f"an integer in [{lo}, {hi}]")
        if not (isinstance(self.near_m, (int, float)) and 0.0 < self.near_m < math.inf):
            raise InputRangeError("near_m", self.near_m, "> 0 metres")
        lo, hi = self.band_nm
        if not 300.0 <= lo < hi <= 1100.0:
            raise InputRangeError("band_nm", self.band_nm, "300 <= lo < hi <= 1100 nm")

    @property
    def fields(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, self.n_fields)

    @property
    def diopters(self) -> np.ndarray:
        """Decreasing, the last 0 (infinity)."""
        return np.linspace(1.0 / self.near_m, 0.0, self.n_depths + 1)

    @property
    def wavelengths_nm(self) -> np.ndarray:
        return np.linspace(*self.band_nm, self.n_wavelengths)


# --------------------------------------------------------------- polynomials
def exponents(degree: int, parity: int) -> np.ndarray:
    """(n, 2) exponents (a, b) of the monomials u^a v^b with a + b <= degree
    and a of ``parity`` (1: odd in u, the sagittal x; 0: even, y)."""
    return np.array([(a, b) for a in range(degree + 1) for b in range(degree + 1 - a) if a % 2 == parity],
                    np.int64).reshape(-1, 2)


def monomials(u: np.ndarray, v: np.ndarray, degree: int, parity: int) -> np.ndarray:
    """(P, n) the monomials of :func:`exponents` at points (u, v) (P,)."""
    e = exponents(degree, parity)
    top = degree + 1
    pu = u[:, None] ** np.arange(top)                # (P, degree + 1)
    pv = v[:, None] ** np.arange(top)
    return pu[:, e[:, 0]] * pv[:, e[:, 1]]


def monomial_set(uv: np.ndarray, recipe: "RayMapRecipe") -> dict:
    """{(degree, parity): monomials (P, n)} of every polynomial a map of
    ``recipe`` evaluates, at stop points ``uv`` (P, 2)."""
    u, v = uv[:, 0], uv[:, 1]
    return {(deg, p): monomials(u, v, deg, p)
            for deg in {recipe.degree, recipe.chroma_degree, recipe.clip_degree} for p in (0, 1)}


class _MonomialCache:
    """The last few stop grids' :func:`monomial_set` (a library evaluates one
    grid for every depth bin; a refocus or a new pitch keeps it)."""

    def __init__(self, size: int = 4):
        self.size, self.kept = size, {}

    def __call__(self, uv: np.ndarray, recipe) -> dict:
        key = (uv.shape, hash(uv.tobytes()), recipe)
        if key not in self.kept:
            while len(self.kept) >= self.size:
                self.kept.pop(next(iter(self.kept)))
            self.kept[key] = monomial_set(uv, recipe)
        return self.kept[key]


_MONOMIALS = _MonomialCache()
caches.register("raymap monomials", _MONOMIALS.kept.clear, lambda: len(_MONOMIALS.kept))


def n_terms(degree: int) -> tuple[int, int]:
    """(odd, even) monomial counts of a degree."""
    return len(exponents(degree, 1)), len(exponents(degree, 0))


def _fit(m: np.ndarray, values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares coefficients (n,) of ``values`` (P,) on the monomials
    ``m`` (P, n) where ``mask``; zeros where too few points hold it. Returns
    the coefficients and the fit's largest residual (mm)."""
    if mask.sum() < 2 * m.shape[1]:
        return np.zeros(m.shape[1]), 0.0
    c, *_ = np.linalg.lstsq(m[mask], values[mask], rcond=None)
    return c, float(np.abs(m[mask] @ c - values[mask]).max())


# ------------------------------------------------------------------- the map
class RayMap:
    """One lens's ray map (see the module's docstring). ``coeffs``: name ->
    array: 'xy' (D+1, F, W, 2, n_odd + n_even) the landing point on the
    sensor as traced and on the sensor focused at the recipe's near limit
    (``meta['far_plane_mm']`` behind it; between and beyond the two planes a
    ray is a straight line), 'clip' (D+1, F, K, ...) each clipping surface,
    all float32; 'chief' (D+1, F, 2) the design wavelength's chief ray (height
    mm, slope dy/dz), 'geometry' (D+1, F) and 'reference_geometry' (D+1,) the
    relative illumination's geometry (``compute._illumination_geometry``),
    'ok' (D+1, F) the sources that exist."""

    def __init__(self, meta: dict, arrays: dict, path: str | None = None):
        self.meta, self.arrays, self.path = meta, arrays, path
        self.recipe = RayMapRecipe(**{k: (tuple(v) if k == "band_nm" else v) for k, v in meta["recipe"].items()})
        self.diopters = self.recipe.diopters
        self.fields = self.recipe.fields
        self.wavelengths_nm = self.recipe.wavelengths_nm
        self.clip_surfaces = list(meta["clip_surfaces"])
        self.clear_mm = np.asarray(meta["clear_mm"], np.float64)
        # the arrays at the depths asked for lately: every library of a job (the image's, a large blur's,
        # the coarse layers', a kernel grown to fit) asks for the same bins' depths
        self._depths: dict = {}

    @property
    def lens_id(self) -> str:
        return self.meta["lens_id"]

    @property
    def stop_radius_mm(self) -> float:
        return float(self.meta["stop_semi_diameter_mm"])

    @property
    def near_m(self) -> float:
        return self.recipe.near_m

    # ------------------------------------------------------------- the lens
    def wide_open(self, lens: Lens) -> tuple[Lens, float]:
        """(the lens with its stop as prescribed, the stop's radius as a
        fraction of the prescribed one): a stopped-down lens (``aperture.
        stopped_down``) is the map's lens with a smaller or bladed stop."""
        i = lens.stop_index
        stop = lens.surfaces[i]
        r0 = self.stop_radius_mm
        opened = replace(stop, semi_diameter_mm=r0, blades=0, blade_rotation_deg=0.0)
        return lens.with_surfaces(lens.surfaces[:i] + (opened,) + lens.surfaces[i + 1:]), \
            stop.semi_diameter_mm / r0

    def check_lens(self, lens: Lens) -> float:
        """The stop's fraction of the prescribed radius; refuses another
        prescription (or a stop opened wider than prescribed)."""
        opened, ratio = self.wide_open(lens)
        fp = lens_fingerprint(opened)
        if lens.id != self.lens_id or fp != self.meta["lens_fingerprint"]:
            raise OpticsError(f"{self.path}: built for {self.lens_id} ({self.meta.get('lens_file')}; fingerprint "
                              f"{self.meta['lens_fingerprint'][:12]}...), not {lens.id} ({lens.path}; "
                              f"{fp[:12]}...): trace its PSFs instead")
        if ratio > 1.0 + 1e-9:
            raise OpticsError(f"{lens.path}: its stop ({lens.surfaces[lens.stop_index].semi_diameter_mm:.6g} mm) "
                              f"is wider than the {self.stop_radius_mm:.6g} mm {self.path} was traced with")
        return ratio

    def sensor_shift_mm(self, lens: Lens, focus_m: float | None) -> float:
        """dz (mm): the sensor of ``lens`` focused at ``focus_m`` (None: as
        prescribed) behind the one the map was traced at."""
        if focus_m is None:
            return 0.0
        q = float(image_distance_mm(lens, focus_m))
        if not (math.isfinite(q) and q > 0):
            raise InputRangeError("focus_distance_m", focus_m, "a distance whose image is real and behind the lens")
        return q - float(self.meta["sensor_distance_mm"])

    # ------------------------------------------------------------ evaluation
    def _at_depth(self, diopters: float) -> dict:
        """Every array at one depth (1/m), interpolated in diopters
        (:data:`GRID_NODES`-point Lagrange)."""
        g = self.diopters
        x = min(max(diopters, 0.0), g[0])
        if x in self._depths:
            return self._depths[x]
        if len(self._depths) >= 64:
            self._depths.clear()
        self._depths[x] = out = self._interpolated(x)
        return out

    def _interpolated(self, x: float) -> dict:
        g = self.diopters
        pos = np.array([(g[0] - x) / (g[0] - g[-1]) * (len(g) - 1)])
        idx, w = grid_weights(pos, len(g))
        idx, w = idx[0], w[0]
        out = {k: np.tensordot(w, self.arrays[k][idx].astype(np.float64), axes=1)
               for k in ("xy", "chroma", "clip", "chief", "geometry", "reference_geometry")}
        # the reachable disc linear between neighbours: a cubic's overshoot would cut reachable rays
        (i2,), (w2,) = grid_weights(pos, len(g), nodes=2)
        out["aim"] = np.tensordot(w2, self.arrays["aim"][i2], axes=1)
        out["ok"] = self.arrays["ok"][idx].all(axis=0)
        return out

    def rays(self, depth_m: float, fields, dz_mm: float, uv: np.ndarray, wavelengths_nm, semi_diagonal_mm: float,
             mono: dict | None = None):
        """The rays of sources at one depth (m, ``inf`` allowed) and
        ``fields`` (S,) on the sensor moved by ``dz_mm``, launched at ``uv``
        (P, 2) (stop coordinates / the prescribed stop radius): returns x, y
        (S, W, P) mm on that sensor (float64), valid (S, W, P), the chief
        ray's height (S,) mm, the illumination geometry (S,) and its axial
        reference (a number). ``mono``: :func:`monomial_set` of ``uv`` (made
        here if None; a library that evaluates many sources makes it once)."""
        d = float(depth_m)
        at = self._at_depth(0.0 if math.isinf(d) else 1.0 / d)
        f = np.asarray(fields, np.float64)
        # the field on the moved sensor: the store field whose chief ray lands there (monotone in field)
        heights = at["chief"][:, 0] + dz_mm * at["chief"][:, 1]
        h0 = np.interp(f * semi_diagonal_mm, heights, self.fields)
        idx, wf = grid_weights(h0 * (len(self.fields) - 1), len(self.fields))       # (S, n)

        def along_field(a):
            return np.einsum("sn,sn...->s...", wf, a[idx])
        xy, chroma, clip = along_field(at["xy"]), along_field(at["chroma"]), along_field(at["clip"])
        chief = along_field(at["chief"])
        i2, w2 = grid_weights(h0 * (len(self.fields) - 1), len(self.fields), nodes=2)
        reach = np.einsum("sn,sn...->s...", w2, at["aim"][i2])
        geo = along_field(at["geometry"])
        ok = at["ok"][idx].all(axis=1)
        u, v = uv[:, 0], uv[:, 1]
        r = self.recipe
        no, ne = n_terms(r.degree)
        mono = _MONOMIALS(uv, r) if mono is None else mono
        mo, me = mono[r.degree, 1], mono[r.degree, 0]
        # the two planes mixed: a ray is straight behind the last surface
        a = dz_mm / float(self.meta["far_plane_mm"])
        plane = (1.0 - a) * xy[..., 0, :] + a * xy[..., 1, :]                 # (S, n)
        dplane = (1.0 - a) * chroma[..., 0, :] + a * chroma[..., 1, :]       # (S, Ws, n')
        ho, he = n_terms(r.chroma_degree)
        x = (plane[..., :no] @ mo.T)[:, None, :] + dplane[..., :ho] @ mono[r.chroma_degree, 1].T
        y = (plane[..., no:] @ me.T)[:, None, :] + dplane[..., ho:] @ mono[r.chroma_degree, 0].T
        # (S, Ws, P) at the stored wavelengths -> the asked ones, linear in wavelength
        a = _wavelength_weights(np.asarray(wavelengths_nm, np.float64), self.wavelengths_nm)
        x = np.einsum("wk,skp->swp", a, x)
        y = np.einsum("wk,skp->swp", a, y)
        valid = ok[:, None] & (u * u + v * v + reach[:, :1] * v + reach[:, 1:] <= 0.0)
        co, ce = n_terms(r.clip_degree)
        mco, mce = mono[r.clip_degree, 1], mono[r.clip_degree, 0]
        for k, clear in enumerate(self.clear_mm):
            xk, yk = clip[:, k, :co] @ mco.T, clip[:, k, co:] @ mce.T
            valid &= xk * xk + yk * yk <= clear * clear
        valid = np.broadcast_to(valid[:, None, :], x.shape)
        cy = chief[:, 0] + dz_mm * chief[:, 1]
        return x, y, valid, np.where(ok, cy, 0.0), np.where(ok, geo, 0.0), float(at["reference_geometry"])

    # --------------------------------------------------------------- storage
    def save(self, path) -> None:
        """Write the map (refused, nothing written, where no grid point is usable: a lens no ray passes)."""
        if not np.asarray(self.arrays["ok"]).any():
            raise OpticsError(f"{path}: a ray map of {self.lens_id} would hold no usable source (no ray of the lens "
                              "reaches the sensor at any field and depth of its grid): not written")
        write_format(path, self.meta, {k: np.asarray(v) for k, v in self.arrays.items()}, FORMAT, FORMAT_VERSION)

    @classmethod
    def load(cls, path) -> "RayMap":
        """A ray map file, read by the shared checked reader (``io.npzfile``:
        size limits, headers before data, no pickle, finite values), its
        format, version and checksum, then every field it serves from."""
        path = Path(path)

        def fail(message, field=None, allowed=None):
            return RayMapFileError(file_error_text(path, message, field, allowed))
        meta, arrays = read_format(path, fail, FORMAT, FORMAT_VERSION)
        _check(meta, arrays, fail)
        return cls(meta, arrays, str(path))


# between grid points (fields, depths): Lagrange through this many nearest (4: cubic)
GRID_NODES = 4


def grid_weights(pos: np.ndarray, n: int, nodes: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(indices (S, m), weights (S, m)): Lagrange interpolation at fractional
    positions ``pos`` (S,) of a uniform grid of ``n`` points through the
    ``m`` = :data:`GRID_NODES` nearest (exact at a grid point)."""
    m = min(GRID_NODES if nodes is None else nodes, n)
    pos = np.clip(np.asarray(pos, np.float64), 0.0, n - 1)
    j0 = np.clip(np.floor(pos).astype(np.int64) - (m - 1) // 2, 0, n - m)
    idx = j0[:, None] + np.arange(m)
    w = np.ones(idx.shape)
    for k in range(m):
        for q in range(m):
            if q != k:
                w[:, k] *= (pos - idx[:, q]) / (idx[:, k] - idx[:, q])
    return idx, w


# landing points between stored wavelengths: Lagrange through this many nearest (3: quadratic)
WAVELENGTH_NODES = 3


def _wavelength_weights(asked: np.ndarray, stored: np.ndarray, nodes: int | None = None) -> np.ndarray:
    """(W, Ws): each asked wavelength as the Lagrange polynomial through its
    ``nodes`` nearest stored wavelengths (exact at a stored one)."""
    n = min(WAVELENGTH_NODES if nodes is None else nodes, len(stored))
    a = np.zeros((len(asked), len(stored)))
    for i, w in enumerate(asked):
        j0 = int(np.clip(np.searchsorted(stored, w) - n // 2, 0, len(stored) - n))
        idx = np.arange(j0, j0 + n)
        for j in idx:
            others = idx[idx != j]
            a[i, j] = np.prod((w - stored[others]) / (stored[j] - stored[others]))
    return a


# the largest coefficient (and chief ray, aim point) a ray map may hold, mm: a position 100 m off the axis
MAX_COEFFICIENT_MM = 1e5


def _check(meta: dict, arrays: dict, fail) -> None:
    """Every field of a ray map's metadata that serving reads, in its range,
    and its arrays shaped as its recipe says."""
    rp, n_clip = check_map_meta(meta, fail)
    rows = (rp.n_depths + 1, rp.n_fields)
    no, ne = n_terms(rp.degree)
    co, ce = n_terms(rp.clip_degree)
    check_array(arrays, "xy", rows + (2, no + ne), fail)
    ho, he = n_terms(rp.chroma_degree)
    check_array(arrays, "chroma", rows + (rp.n_wavelengths, 2, ho + he), fail)
    check_array(arrays, "clip", rows + (n_clip, co + ce), fail)
    check_array(arrays, "chief", rows + (2,), fail)
    check_array(arrays, "geometry", rows, fail)
    check_tables(arrays, rp, fail)
    # served positions are sums of these over monomials of at most 1 in magnitude: bounded here, they stay finite
    # and within any integer conversion's range (coefficients scaled by 1e30 once ended in an OverflowError)
    for name in ("xy", "chroma", "clip", "chief"):
        check_bounded(arrays, name, MAX_COEFFICIENT_MM, fail)


def check_bounded(arrays: dict, name: str, limit: float, fail, unit: str = " mm") -> None:
    """``arrays[name]`` finite and at most ``limit`` in magnitude."""
    a = arrays[name]
    if a.size and not (np.isfinite(a).all() and np.abs(a).max() <= limit):
        worst = float(np.nanmax(np.abs(np.where(np.isfinite(a), a, np.inf))))
        raise fail(f"array {name!r} holds {worst:.3g}", field=name,
                   allowed=f"finite values of at most {limit:g}{unit} in magnitude")


def check_tables(arrays: dict, rp: "RayMapRecipe", fail) -> None:
    """The tables a map serves beside its fits, on its grid: the reachable
    disc ('aim'), the usable sources ('ok', one at least) and the axial
    illumination ('reference_geometry')."""
    rows = (rp.n_depths + 1, rp.n_fields)
    check_array(arrays, "aim", rows + (2,), fail)
    check_array(arrays, "reference_geometry", rows[:1], fail)
    ok = check_array(arrays, "ok", rows, fail, kinds="b")
    if not ok.any():                 # it would serve empty kernels at every field and depth
        raise fail("no grid point of the map is usable (every source marked unreachable)", field="ok",
                   allowed="a map with a usable source")
    check_bounded(arrays, "aim", MAX_COEFFICIENT_MM, fail)


def check_map_meta(meta: dict, fail) -> tuple["RayMapRecipe", int]:
    """A ray map's metadata that serving reads, each field in its range: (its recipe, the clipping surfaces)."""
    rec = Record(meta, fail)
    rec.name("lens_id")
    rec.text("lens_fingerprint", max_chars=128)
    rec.number("stop_semi_diameter_mm", 0.0, 1e4, lo_open=True)
    rec.number("sensor_distance_mm", 0.0, 1e5, lo_open=True)
    far = rec.number("far_plane_mm", -1e5, 1e5)
    if abs(far) < 1e-6:
        raise fail(f"far_plane_mm {far!r}", field="far_plane_mm", allowed="a plane off the sensor (|dz| > 1e-6 mm)")
    r = rec.sub("recipe")
    r.allowed_keys([f for f in RayMapRecipe.__dataclass_fields__])
    recipe = {"n_fields": r.integer("n_fields", 2, 256), "n_depths": r.integer("n_depths", 1, 256),
              "near_m": r.number("near_m", 0.0, 1e6, lo_open=True),
              "n_wavelengths": r.integer("n_wavelengths", 2, 64),
              "band_nm": tuple(r.numbers("band_nm", 300.0, 1100.0, (2, 2))),
              "degree": r.integer("degree", 1, 21), "chroma_degree": r.integer("chroma_degree", 1, 21),
              "clip_degree": r.integer("clip_degree", 1, 21), "fit_samples": r.integer("fit_samples", 8, 1024)}
    try:
        rp = RayMapRecipe(**recipe)
    except InputRangeError as e:
        raise fail(str(e), field="recipe") from None
    n_clip = len(rec.integers("clip_surfaces", 0, 1024, (0, 1024)))
    rec.numbers("clear_mm", 0.0, 1e4, (n_clip, n_clip), lo_open=True)
    return rp, n_clip


# -------------------------------------------------------------------- build
def build(lens: Lens, recipe: RayMapRecipe | None = None, *, progress=None, precise: bool = False) -> RayMap:
    """Trace ``lens`` (as prescribed, wide open) at the recipe's grid and fit
    its ray map. ``progress(done, total)`` per depth. ``precise``: the fits
    kept in float64 (a study's data; a shipped map holds the landing and
    clipping fits in float32, the chromatic differences in float16)."""
    recipe = recipe or RayMapRecipe()
    t_start = time.perf_counter()
    if lens.surfaces[lens.stop_index].blades:
        raise InputRangeError("lens", lens.iris or "a bladed stop", "the lens as prescribed, round and wide open")
    r0 = lens.surfaces[lens.stop_index].semi_diameter_mm
    targets = stop_grid(lens, recipe.fit_samples)
    uv = targets / r0
    u, v = uv[:, 0], uv[:, 1]
    m = monomial_set(uv, recipe)
    wl = recipe.wavelengths_nm
    dio = recipe.diopters
    depths = np.where(dio > 0, 1.0 / np.where(dio > 0, dio, 1.0), np.inf)
    fields = recipe.fields
    nd, nf, nw = len(depths), len(fields), len(wl)
    cands = [k for k in range(len(lens.surfaces)) if k != lens.stop_index]
    no, ne = n_terms(recipe.degree)
    co, ce = n_terms(recipe.clip_degree)
    xy = np.zeros((nd, nf, 2, no + ne))
    ho, he = n_terms(recipe.chroma_degree)
    chroma = np.zeros((nd, nf, nw, 2, ho + he))
    far = float(image_distance_mm(lens, recipe.near_m)) - float(lens.surfaces[-1].thickness_mm)
    if not (math.isfinite(far) and abs(far) > 1e-6):
        raise InputRangeError("near_m", recipe.near_m, f"a focus distance that moves {lens.id}'s sensor")
    clipc = np.zeros((nd, nf, len(cands), co + ce))
    stopped = np.zeros((nd, nf, len(targets)), bool)                      # what the clear apertures stop
    unreached = np.zeros((nd, nf, len(targets)), bool)                    # what the reachable disc leaves out
    cut = np.zeros((nd, nf, len(cands), len(targets)), bool)              # what each fitted surface stops
    chief = np.zeros((nd, nf, 2))
    aim = np.tile(np.array([0.0, -(1.0 + AIM_MARGIN) ** 2]), (nd, nf, 1))   # the unit pupil: every target reachable
    geometry = np.zeros((nd, nf))
    reference = np.zeros(nd)
    ok = np.zeros((nd, nf), bool)
    worst = 0.0
    for i, depth in enumerate(depths):
        aimed = sources(lens, [depth], field=fields)                       # (F, 1)
        o, d, status, _ = pupil_rays(lens, aimed, targets)                 # (F, 1, P, 3)
        o, d, status = o[:, 0], d[:, 0], status[:, 0]
        b = trace(lens, o[:, None], d[:, None], wl[None, :, None], status=status[:, None])    # (F, W, P)
        oc, dc, sc, _ = pupil_rays(lens, aimed, np.zeros((1, 2)))
        cb = trace(lens, oc[:, 0, 0], dc[:, 0, 0], lens.wavelength_nm, apertures=False, status=sc[:, 0, 0])
        for j in range(nf):
            live = b.valid[j]
            if not (aimed.ok[j, 0] and cb.valid[j] and live[nw // 2].sum() >= 4 * (no + ne)):
                continue
            ok[i, j] = True
            pos, dirn = b.position_mm[j], b.direction[j]                     # (W, P, 3)
            mid = nw // 2
            for q, dz in enumerate((0.0, far)):
                with np.errstate(invalid="ignore", divide="ignore"):
                    px = pos[..., 0] + dz * dirn[..., 0] / dirn[..., 2]      # (W, P)
                    py = pos[..., 1] + dz * dirn[..., 1] / dirn[..., 2]
                cx, e1 = _fit(m[recipe.degree, 1], px[mid], live[mid])
                cyy, e2 = _fit(m[recipe.degree, 0], py[mid], live[mid])
                xy[i, j, q] = np.concatenate([cx, cyy])
                worst = max(worst, e1, e2)
                # the other wavelengths: their difference from the middle one, a smoother function
                for w in range(nw):
                    both = live[w] & live[mid]
                    if w != mid:
                        chroma[i, j, w, q] = np.concatenate(
                            [_fit(m[recipe.chroma_degree, 1], px[w] - px[mid], both)[0],
                             _fit(m[recipe.chroma_degree, 0], py[w] - py[mid], both)[0]])
            cd = cb.direction[j]
            chief[i, j] = (cb.position_mm[j, 1], cd[1] / cd[2])
        # where a clipping surface meets the rays: only rays that reach their stop target (a ray the
        # aiming could not steer there, one that misses a surface, is somewhere else on every surface)
        sb = trace(lens, o, d, lens.wavelength_nm, apertures=False, upto_surface=lens.stop_index, status=status)
        aimed_ok = sb.valid & (np.hypot(sb.position_mm[..., 0] - targets[:, 0],
                                        sb.position_mm[..., 1] - targets[:, 1]) <= AIM_TOLERANCE * r0)
        stopped[i] = ~trace(lens, o, d, lens.wavelength_nm, status=status).valid
        for j in np.flatnonzero(ok[i]):
            aim[i, j] = _reachable(u, v, aimed_ok[j])
            unreached[i, j] = u * u + v * v + aim[i, j, 0] * v + aim[i, j, 1] > 0.0
        for k, s in enumerate(cands):
            kb = trace(lens, o, d, lens.wavelength_nm, apertures=False, upto_surface=s, status=status)   # (F, P)
            clear = lens.surfaces[s].semi_diameter_mm
            for j in np.flatnonzero(ok[i]):
                lv = kb.valid[j] & aimed_ok[j]
                cx = _fit(m[recipe.clip_degree, 1], kb.position_mm[j, :, 0], lv)[0]
                cyy = _fit(m[recipe.clip_degree, 0], kb.position_mm[j, :, 1], lv)[0]
                clipc[i, j, k] = np.concatenate([cx, cyy])
                cut[i, j, k] = np.hypot(m[recipe.clip_degree, 1] @ cx, m[recipe.clip_degree, 0] @ cyy) > clear
        flat = type(aimed)(aimed.depth_mm[:, 0], aimed.p[:, 0], aimed.v_chief[:, 0], aimed.ok[:, 0], aimed.z_ep)
        geometry[i] = np.where(ok[i], _illumination_geometry(lens, flat, chief[i, :, 0]), 0.0)
        ref = aim_chief(lens, np.array([aimed.depth_mm[0, 0]]), np.zeros(1))
        reference[i] = float(_illumination_geometry(lens, ref, np.zeros(1))[0])
        if progress:
            progress(i + 1, nd)
    chosen, mismatch = _cover(stopped[ok], cut[ok], unreached[ok])
    clip = [cands[k] for k in chosen]
    clipc = clipc[:, :, chosen]
    meta = {"lens_id": lens.id, "lens_file": str(lens.path), "lens_fingerprint": lens_fingerprint(lens),
            "stop_semi_diameter_mm": float(r0), "sensor_distance_mm": float(lens.surfaces[-1].thickness_mm),
            "far_plane_mm": far,
            "recipe": {**asdict(recipe), "band_nm": list(recipe.band_nm)},
            "clip_surfaces": [int(s) for s in clip],
            "clear_mm": [float(lens.surfaces[s].semi_diameter_mm) for s in clip],
            "fit_worst_mm": worst, "mask_mismatch": mismatch, "build_s": time.perf_counter() - t_start}
    stored = (np.float64,) * 3 if precise else (np.float32, np.float16, np.float32)
    arrays = {"xy": xy.astype(stored[0]), "chroma": chroma.astype(stored[1]), "clip": clipc.astype(stored[2]),
              "chief": chief, "aim": aim, "geometry": geometry, "reference_geometry": reference, "ok": ok}
    return RayMap(meta, arrays)


def _reachable(u: np.ndarray, v: np.ndarray, reached: np.ndarray) -> np.ndarray:
    """(A, B): the disc u^2 + v^2 + A v + B <= 0 (its centre on the
    meridional axis) that holds every stop target a ray reached (``reached``)
    and leaves out the most of those none could: where the aiming finds no
    ray (one that would miss a surface before the stop), there is none, and
    no clear aperture's fit need say so. Every target reached: the unit pupil."""
    if reached.all() or not reached.any():
        return np.array([0.0, -(1.0 + AIM_MARGIN) ** 2])
    c = AIM_CENTRES[:, None]
    dist = np.hypot(u[None, :], v[None, :] - c)                         # (C, P)
    radius = dist[:, reached].max(axis=1) + AIM_MARGIN
    left_out = (dist[:, ~reached] > radius[:, None]).sum(axis=1)
    best = int(np.flatnonzero(left_out == left_out.max())[np.argmin(np.abs(AIM_CENTRES[left_out == left_out.max()]))])
    cb, rb = float(AIM_CENTRES[best]), float(radius[best])
    return np.array([-2.0 * cb, cb * cb - rb * rb])


def _cover(stopped: np.ndarray, cut: np.ndarray, start: np.ndarray) -> tuple[list[int], float]:
    """The fewest candidate surfaces whose fitted clear apertures stop what
    the lens's clear apertures stop: ``stopped`` (n, P) the fit grid's rays
    the trace stops (any surface, or aiming that found no path) at n sources,
    ``cut`` (n, K, P) those each candidate's fitted heights put outside its
    clear aperture, ``start`` (n, P) those the reachable disc leaves out
    already. Greedy: the candidate that stops the most rays still
    wrongly passed, less those it wrongly stops, while that is positive.
    Returns the chosen indices and the fraction of rays the choice still
    misjudges (either way)."""
    passed = start.copy()                             # the cover's verdict: stopped so far
    chosen: list[int] = []
    while True:
        wrong_pass = stopped & ~passed
        gain = (cut & wrong_pass[:, None, :]).sum(axis=(0, 2)) - (cut & ~stopped[:, None, :] & ~passed[:, None, :]).sum(
            axis=(0, 2))
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(k)
        passed |= cut[:, k]
    return sorted(chosen), float((passed != stopped).mean()) if stopped.size else 0.0


# ------------------------------------------------------------------ serving
class RayMapLibrary(PSFLibrary):
    """A PSF library of one lens whose bins are deposited from its ray map
    (never traced): the traced library's grid and interface, at any pixel
    pitch, kernel size, focus and stop (f-number, blades) of that lens."""

    def __init__(self, raymap: RayMap, lens: Lens, settings: PSFSettings, grid: LibraryGrid | None = None,
                 response=None):
        ratio = raymap.check_lens(lens)
        grid = grid or LibraryGrid()
        if grid.near_m < raymap.near_m - 1e-9:
            raise InputRangeError("library grid near limit", grid.near_m,
                                  f">= {raymap.near_m} m, the nearest depth {raymap.path} holds")
        lo, hi = raymap.recipe.band_nm
        wl, _ = spectral_samples(settings, response)
        if wl.min() < lo - 1e-9 or wl.max() > hi + 1e-9:
            raise InputRangeError("wavelengths", (float(wl.min()), float(wl.max())),
                                  f"within {lo:g}-{hi:g} nm, the band {raymap.path} holds")
        self.raymap, self.stop_ratio = raymap, ratio
        self.dz_mm = raymap.sensor_shift_mm(lens, settings.focus_distance_m)
        super().__init__(lens, settings, grid, response)
        self.meta["format"] = "raymap"
        self.meta["raymap_file"] = raymap.path
        self.last_timings_s = {}

    def _deposit(self, depth_m: float, fields) -> dict:
        """The kernels and figures of ``fields`` (S,) at one depth, batched over rays."""
        lens, s = self.lens, self.settings
        uv = stop_grid(lens, s.pupil_samples) / self.raymap.stop_radius_mm
        mono = _MONOMIALS(uv, self.raymap.recipe)
        wl, w = np.asarray(self.meta["wavelengths_nm"]), np.asarray(self.meta["channel_weights"])
        pitch = pixel_pitch_mm(lens, s)
        sd = lens.sensor.semi_diagonal_mm
        per = max(1, BATCH_RAYS // (len(uv) * len(wl)))
        parts = []
        for start in range(0, len(fields), per):
            f = np.asarray(fields[start:start + per], np.float64)
            x, y, valid, cy, geo, ref = self.raymap.rays(depth_m, f, self.dz_mm, uv, wl, sd, mono)
            kern = rays_to_kernels(x, y, valid, cy, w, len(uv), pitch, s)
            vig = np.clip(kern.vignetted_fraction, 0.0, 1.0)
            ri = geo * (1.0 - vig[:, 1]) / ref if ref > 0 else np.zeros(len(f))
            parts.append({"psf": kern.psf, "energy_outside": np.clip(kern.energy_outside, 0.0, 1.0),
                          "vignetted_fraction": vig, "relative_illumination": ri, "chief_ray_height_mm": cy,
                          "zero_energy": ~(vig < 1.0).any(-1), "kernel_size_needed": kern.kernel_size_needed})
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _compute(self, todo: list[int], progress) -> None:
        """Deposit the depth bins ``todo`` from the ray map."""
        t0 = time.perf_counter()
        total = len(todo) * len(self.fields)
        for n, b in enumerate(todo):
            out = self._deposit(self.depths_m[b], self.fields)
            for k, v in out.items():
                getattr(self, k)[b] = v
            self.computed[b] = True
            if progress or self.progress:
                (progress or self.progress)((n + 1) * len(self.fields), total)
        self.last_timings_s = {"raymap": time.perf_counter() - t0}

    def kernels(self, field, depth_m) -> np.ndarray:
        """PSFs (..., 3, k, k) at fields x depths (broadcast), deposited from
        the ray map at those very points (no library grid between)."""
        f, d = np.broadcast_arrays(np.asarray(field, np.float64), np.asarray(depth_m, np.float64))
        if not np.isfinite(f).all() or (f < 0).any() or (f > 1.0 + 1e-9).any():
            raise InputRangeError("field", float(np.nanmax(np.abs(f))), "[0, 1] (1 = sensor half-diagonal)")
        if not (d > 0).all() or (d < self.raymap.near_m).any():
            raise InputRangeError("depth_m", float(np.nanmin(d)), f">= {self.raymap.near_m} m, the nearest depth "
                                                                   f"{self.raymap.path} holds, or inf")
        k = self.kernel_size
        out = np.zeros(f.shape + (3, k, k), np.float32)
        outside, needed, zero = [], [], []
        for depth in np.unique(d):
            at = d == depth
            got = self._deposit(float(depth), np.minimum(f[at], 1.0))
            out[at] = got["psf"]
            outside.append(got["energy_outside"].ravel())
            needed.append(got["kernel_size_needed"].ravel())
            zero.append(got["zero_energy"].ravel())
        if np.concatenate(zero).all():      # as a trace says it: no kernel to serve
            raise OpticsError(f"no ray of {self.lens.id} reaches the sensor at field {float(f.max()):g}, depth "
                              f"{float(d.min()):g} m: the kernel would be empty")
        # the same warning as a traced kernel's (psf.compute): a clipped kernel is not rescaled to 1 in silence
        text = clip_message(np.concatenate(outside), np.concatenate(needed), k)
        if text:
            warnings.warn(text, KernelTooSmallWarning, stacklevel=2)
        return out

    def at_geometry(self, geometry, settings: PSFSettings | None = None, *, fit_depth_m=None,
                    progress=None) -> "RayMapLibrary":
        """``PSFLibrary.at_geometry``'s PSFs deposited from this library's ray
        map (never traced): at ``geometry``'s pitch, with ``settings``
        (default: this library's), its kernel grown to hold ``fit_depth_m``'s blur.
        At this library's own settings it is this library, with the bins it
        has made (a source kept between jobs makes them once)."""
        s = replace(settings or self.settings, pixel_pitch_mm=geometry.pixel_pitch_mm)

        def make(st):
            return self if st == self.settings else RayMapLibrary(self.raymap, self.lens, st, self.grid, self.response)
        return _fitted(make, s, fit_depth_m, progress)

    def save(self, path) -> None:        # the ray map is the store
        raise OpticsError("a ray-map library is not saved; it is computed from its ray map file")


_MAPS = FileCache(RayMap.load, 4, "ray maps")


def open_raymap(path) -> RayMap:
    """``RayMap.load``, kept for the next request of the same file."""
    try:
        return _MAPS(path)
    except OSError as e:
        raise RayMapFileError(f"{path}: not a readable ray map file ({type(e).__name__}: {e.strerror})") from None


__all__ = ["RayMap", "RayMapRecipe", "RayMapLibrary", "RayMapFileError", "build", "open_raymap"]
