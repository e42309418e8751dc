"""`python -m lab report psf-source`: every PSF source's error against its storage and time.

Candidates, per lens, each scored at the lens's basis pitch (the sensor's,
or the coarser one its basis is stored at) against reference kernels traced
with ``REF_RAYS`` rays per pupil side (16 x the shipped 256, 256 x the
default 64: the default trace's own ray noise is 10-45 dB on the paper's
scale at near depths, so a 64-ray reference would score the noise):

- ``basis r``: the lens's traced library (the shipped recipe: rays, grid,
  kernel) as a rank-r basis + coefficients (``psf.basis``), float16, for
  several ranks; the shipped rank also in float32;
- ``library``: the same traced library uncompressed (float32; what a rank
  as large as the data would give);
- ``trace (default)``: the library the renderer traces today without a
  basis (64 rays, 20 depth bins x 64 fields), at the same pixel pitch and
  kernel size;
- ``OLF``: the shipped Omni-Lens-Field (its kernels area-resampled where the
  basis pitch is coarser than the one it learned).

Figures: PSNR on the paper's scale (each channel divided by its peak,
8-bit; and unquantised, "float"), mean and worst over off-grid points
(uniform in field and diopters, a tenth at infinity, never grid points),
SSIM (8-bit), relative L1; a random 1 % of each source's own grid against
the kernels it was built from (the paper's protocol: for a basis that is
its compression error, for the OLF its fit); storage (the bytes of its
compressed .npz); build minutes (the library's trace; from a cache, estimated
from PSFs traced now); the time of a 1280 x 1920 PSF map (the
basis's or network's part and the whole map); downstream, a simulation and
an occlusion-aware bokeh of the built-in synthetic scene with each source
against the same with traced PSFs (image PSNR), and each one's PSNR against
the sharp image beside the traced one's. A kernel smaller than the
reference's is zero-padded: the energy it leaves out counts as error.

References are cached in ``OUT/references-LENS.npz`` (keyed by lens,
settings, points and seed): a second run scores in minutes.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dcdi_core.atomic import atomic_path, save_figure
from . import write_report
from .olf_report import _psnr_image as _psnr, timed_job
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.basis import SHIPPED_RECIPES, BasisLibrary, BasisRecipe, BasisStore, compress, shipped_store
from dcdi_core.psf.basis import traced_library as recipe_library
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.optics.lens import lens_fingerprint

REF_RAYS = 1024
REPORT_SEED = 20261203
RANKS = (16, 32, 64, 96, 128, 144, 160)
PAPER_POINT = {"psnr_8bit": 49.29, "megabytes": 240.0, "label": "paper OLF (4 lenses, 1 % of its grid)"}
LENSES = ("mos-s1", "mos-s2", "6p", "double-gauss")


@dataclass(frozen=True)
class Plan:
    """What a run measures: off-grid points per lens, rays of the references,
    and (``quick``, for tests) small recipes, grids and images instead of the
    shipped ones."""

    points: int = 32
    quick: bool = False

    @property
    def reference_rays(self) -> int:
        return 64 if self.quick else REF_RAYS

    @property
    def ranks(self) -> tuple:
        return (2, 4) if self.quick else RANKS

    def recipe(self, lens_id: str) -> BasisRecipe:
        r = SHIPPED_RECIPES[lens_id]
        return replace(r, rays=16, n_fields=4, n_depths=3, rank=4, near_rays=32 if r.near_rays else None) \
            if self.quick else r

    @property
    def default_grid(self) -> LibraryGrid:
        """The grid the renderer traces without a basis."""
        return LibraryGrid(n_fields=4, n_depths=3) if self.quick else LibraryGrid()

    @property
    def map_size(self) -> tuple:
        return (64, 96) if self.quick else (1280, 1920)

    @property
    def image_size(self) -> tuple:
        return (48, 72) if self.quick else (640, 960)


# ------------------------------------------------------------------ scores
def point_scores(pred, ref) -> dict:
    """Per-point figures of kernels (n, 3, k, k) against references, both
    summing to 1 per channel: PSNR on the paper's scale (each channel over
    its peak), 8-bit and float (mean over channels), relative L1."""
    from dcdi_core.models.common.metrics import quantize_8bit, relative_l1

    def peak(x):
        m = x.max(axis=(-1, -2), keepdims=True)
        return np.divide(x, m, out=np.zeros_like(x), where=m > 0)

    p, r = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    pp, rp = peak(p), peak(r)
    out = {}
    for name, a, b in (("psnr_8bit", quantize_8bit(pp) / 255.0, quantize_8bit(rp) / 255.0), ("psnr_float", pp, rp)):
        mse = ((a - b) ** 2).mean(axis=(-1, -2))
        with np.errstate(divide="ignore"):
            out[name] = np.minimum(np.where(mse > 0, -10.0 * np.log10(np.where(mse > 0, mse, 1.0)), 100.0),
                                   100.0).mean(axis=-1)
    out["rel_l1"] = np.asarray(relative_l1(p, r)).reshape(len(p), -1).mean(axis=-1)
    return out


def summary(pred, ref) -> dict:
    """Mean and worst of :func:`point_scores`, and the mean SSIM (8-bit)."""
    from dcdi_core.models.common.metrics import psf_scores
    s = point_scores(pred, ref)
    out = {"n": int(len(pred))}
    for key in ("psnr_8bit", "psnr_float"):
        out[key] = float(s[key].mean())
        out[key + "_worst"] = float(s[key].min())
    out["rel_l1"] = float(s["rel_l1"].mean())
    out["ssim_8bit"] = psf_scores(pred, ref, scale="sum")["ssim_8bit"]
    return out


def pad_to(kernels, k: int) -> np.ndarray:
    """Kernels (..., 3, k0, k0) zero-padded (k0 < k) or centre-cropped and
    renormalised (k0 > k) to k x k, each channel summing to 1."""
    from dcdi_core.models.olf.data import crop_normalise
    k0 = kernels.shape[-1]
    if k0 >= k:
        return crop_normalise(kernels, k).astype(np.float64)
    h = (k - k0) // 2
    out = np.zeros(kernels.shape[:-2] + (k, k))
    out[..., h:h + k0, h:h + k0] = kernels
    s = out.sum(axis=(-1, -2), keepdims=True)
    return np.divide(out, s, out=np.zeros_like(out), where=s > 0)


def npz_bytes(**arrays) -> int:
    """Size of the arrays as a compressed .npz (what a file of them takes)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.tell()


# ------------------------------------------------------------------ references
def draw_points(n: int, grid: LibraryGrid, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(fields, depths m) of ``n`` off-grid points: uniform in field and in
    diopters over the grid's range, a tenth at infinity."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.0, 1.0, n)
    dio = rng.uniform(1.0 / grid.far_m, 1.0 / grid.near_m, n)
    d = np.where(rng.uniform(size=n) < 0.1, math.inf, 1.0 / dio)
    return f, d


def references(lens, settings: PSFSettings, grid: LibraryGrid, n: int, seed: int, out: Path, log) -> tuple:
    """(fields, depths, kernels (n', 3, K, K)) traced at ``settings`` (their
    rays, pitch and kernel size) at ``n`` points off ``grid``; read from
    ``out`` when the same were traced before."""
    from dcdi_core.models.olf.data import crop_normalise, trace_points
    f, d = draw_points(n, grid, seed)
    key = hashlib.sha256(json.dumps({"lens": lens_fingerprint(lens), "settings": settings.as_dict(), "n": n,
                                     "seed": seed}, sort_keys=True, default=str).encode()).hexdigest()
    path = out / f"references-{lens.id}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) == key:
                return z["field"], z["depth_m"], z["psf"]
    t, c = time.perf_counter(), time.process_time()
    psf, ok = trace_points(lens, settings, f, d)
    f, d, psf = f[ok], d[ok], crop_normalise(psf[ok], settings.kernel_size)
    log(f"  {lens.id}: {len(f)} reference points traced with {settings.pupil_samples} rays in {time.perf_counter() - t:.0f} s "
        f"({time.process_time() - c:.0f} CPU s)")
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, key=np.array(key), field=f, depth_m=d, psf=psf)
    return f, d, psf


# ------------------------------------------------------------------ candidates
def traced_library(lens, settings: PSFSettings, grid: LibraryGrid, log) -> tuple[PSFLibrary, float]:
    """A fully computed traced library (the PSF cache, or traced now: the seconds)."""
    import warnings
    from dcdi_core.psf.compute import KernelTooSmallWarning
    t = time.perf_counter()
    lib = PSFLibrary.open(lens, settings, grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        built = lib.build()
    secs = time.perf_counter() - t if built else 0.0
    if built:
        log(f"  {lens.id}: library {len(lib.depths_m)} x {len(lib.fields)} at {settings.pupil_samples} rays traced "
            f"in {secs:.0f} s")
    return lib, secs


def trace_seconds(lens, settings: PSFSettings, grid: LibraryGrid, log, n: int = 8) -> float:
    """Seconds a library of ``grid`` takes to trace at ``settings`` (it came
    from the cache): ``n`` of its PSFs traced now (fields and depths spread
    over the grid), times the grid's size over ``n``."""
    from dcdi_core.models.olf.data import trace_points
    f = np.linspace(0.0, 1.0, n)
    d = grid.depths_m[np.linspace(0, len(grid.depths_m) - 1, n).round().astype(int)]
    t = time.perf_counter()
    trace_points(lens, settings, f, d)
    per = (time.perf_counter() - t) / n
    total = per * len(grid.depths_m) * len(grid.fields)
    log(f"  {lens.id}: {per * 1e3:.0f} ms per PSF at {settings.pupil_samples} rays -> "
        f"{total / 60:.1f} min for {len(grid.depths_m)} x {len(grid.fields)}")
    return total


def truncated(store: BasisStore, rank: int, dtype=np.float16) -> BasisStore:
    """The store cut to its first ``rank`` basis vectors (the truncated SVD of
    a lower rank), its arrays rounded to ``dtype`` as a file holds them."""
    b = store.basis[:, :rank].astype(dtype).astype(np.float32)
    c = store.coeffs[..., :rank].astype(dtype).astype(np.float32)
    meta = dict(store.meta, rank=int(b.shape[1]))
    return BasisStore(meta, b, c, store.zero_energy, store.path)


def store_bytes(store: BasisStore, dtype=np.float16) -> int:
    """The bytes of the store's file (its arrays as ``BasisStore.save`` writes them, in ``dtype``)."""
    return npz_bytes(**store.file_arrays(dtype))


def grid_sample(lib, rng, fraction: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(bin, field) indices of a random ``fraction`` of a library's grid."""
    nd, nf = lib.psf.shape[:2]
    n = max(1, int(round(fraction * nd * nf)))
    flat = rng.choice(nd * nf, n, replace=False)
    return flat // nf, flat % nf


def lens_rows(lens_id: str, plan: Plan, out: Path, log, olf=None) -> dict:
    """Every candidate's figures for one lens (module docstring)."""
    from dcdi_core.psf.sources import OLFLibrary
    lens = load_lens(lens_id)
    recipe = plan.recipe(lens_id)
    settings = recipe.settings(lens)
    pitch, k_store = settings.pixel_pitch_mm, recipe.kernel_size
    olf_lib = None
    if olf is not None and olf.covers(lens):
        olf_lib = OLFLibrary(olf, lens, pixel_pitch_mm=pitch)
    k_ref = max(k_store, olf_lib.kernel_size if olf_lib is not None else 0)
    f, d, ref = references(lens, replace(settings, kernel_size=k_ref, pupil_samples=plan.reference_rays), recipe.grid,
                           plan.points, REPORT_SEED, out, log)
    rng = np.random.default_rng(REPORT_SEED)
    rows = []

    def add(name, kind, kernels, storage, build_s, grid_scores=None, **extra):
        row = {"name": name, "kind": kind, "megabytes": storage / 1e6, "build_minutes": build_s / 60.0,
               "offgrid": summary(pad_to(kernels, k_ref), ref), "grid": grid_scores, **extra}
        rows.append(row)
        o = row["offgrid"]
        log(f"  {lens_id} {name}: off-grid {o['psnr_8bit']:.2f} dB (worst {o['psnr_8bit_worst']:.2f}), "
            f"{row['megabytes']:.2f} MB")

    lib, secs = recipe_library(lens, recipe, log=log)
    if not secs:
        secs = trace_seconds(lens, settings, recipe.grid, log)
        if recipe.near_rays:            # the near bins again, with more rays
            whole = trace_seconds(lens, replace(settings, pupil_samples=recipe.near_rays), recipe.grid, log)
            secs += whole * len(recipe.near_bins()) / len(recipe.grid.depths_m)
    ranks = sorted(set(plan.ranks) | {recipe.rank})
    full = compress(lib, max(ranks), build_s=secs, ripple_floor=recipe.ripple_floor)
    bi, fi = grid_sample(lib, rng)
    src_grid = pad_to(lib.psf[bi, fi], k_store)
    for r in ranks:
        for dtype in ((np.float16, np.float32) if r == recipe.rank else (np.float16,)):
            st = truncated(full, r, dtype)
            blib = BasisLibrary(st, lens)
            kern = blib.at(f, d)
            grid = summary(st.kernels_at_bins(np.arange(len(lib.depths_m)))[bi, fi], src_grid)
            label = f"basis {r}" + (" (float32)" if dtype == np.float32 else "")
            add(label, "basis", kern, store_bytes(st, dtype), secs, grid, rank=r, dtype=np.dtype(dtype).name,
                shipped=(r == recipe.rank and dtype == np.float16))
    rays = f"{recipe.rays} rays" + (f", {recipe.near_rays} to {recipe.near_until_m:g} m" if recipe.near_rays else "")
    add(f"library ({rays}, uncompressed)", "library", lib.at(f, d),
        npz_bytes(psf=lib.psf), secs, None)
    dset = replace(PSFSettings(kernel_size=k_store), pixel_pitch_mm=pitch)
    default, dsecs = traced_library(lens, dset, plan.default_grid, log)
    dsecs = dsecs or trace_seconds(lens, dset, plan.default_grid, log)
    g = plan.default_grid
    add(f"trace (default: 64 rays, {g.n_depths + 1} x {g.n_fields})", "trace", default.at(f, d), npz_bytes(psf=default.psf), dsecs, None)
    if olf_lib is not None:
        entry = olf.lens_entry(lens_id)
        kern = olf_lib.kernels(f, d, dtype=np.float64)
        grid = None
        if not plan.quick:                   # its training library: 64 rays, 21 x 64, traced
            s_olf = dict(entry["psf_settings"], band_nm=tuple(entry["psf_settings"]["band_nm"]))
            olf_src, _ = traced_library(lens, PSFSettings(**s_olf), LibraryGrid(**entry["library_grid"]), log)
            gi, gf = grid_sample(olf_src, rng)
            gpred = olf.psf(lens, olf_src.fields[gf], olf_src.depths_m[gi], dtype=np.float64)
            grid = summary(gpred, pad_to(olf_src.psf[gi, gf], int(entry["kernel_size"])))
        add("OLF (shipped)", "olf", kern, Path(olf.path).stat().st_size,
            (olf.meta.get("training") or {}).get("seconds", 0.0), grid, shared_by=len(olf.lens_ids))
    return {"lens": lens_id, "pixel_pitch_mm": pitch, "sensor_pitch_mm": pitch / recipe.pitch_factor,
            "kernel_reference": k_ref, "points": int(len(f)), "reference_rays": plan.reference_rays, "rows": rows,
            "recipe": {k: getattr(recipe, k) for k in ("rays", "n_fields", "n_depths", "pitch_factor",
                                                       "kernel_size", "rank")}}


# ------------------------------------------------------------------ time and images
def map_times(lens_id: str, olf, log, plan: Plan) -> dict:
    """Seconds of a PSF map of the synthetic scene's depth at ``size`` (at the
    lens's basis pitch): traced library in memory, the basis (its
    reconstruction part), the OLF (its network part)."""
    from dcdi_core.psf.sources import OLFLibrary
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.psfmap import psf_map
    from dcdi_core.render.synthetic import synthetic_rgbd
    lens = load_lens(lens_id)
    recipe = plan.recipe(lens_id)
    settings = recipe.settings(lens)
    repeat = 1 if plan.quick else 2
    size = fitting_size(lens, settings.pixel_pitch_mm, plan.map_size)
    geom = ImageGeometry.from_pixel_pitch(lens, *size, settings.pixel_pitch_mm)
    _, depth = synthetic_rgbd(*size, seed=0)
    depth = depth.astype(np.float64)
    store = _store(lens_id, plan, lens, log)
    lib, _ = recipe_library(lens, recipe, log=log)
    out = {"image": list(size), "lens": lens_id}
    for name, make in (("library", lambda: lib),
                       ("basis", (lambda: BasisLibrary(store, lens)) if store is not None else None),
                       ("olf", (lambda: OLFLibrary(olf, lens, pixel_pitch_mm=settings.pixel_pitch_mm))
                        if olf is not None and olf.covers(lens) else None)):
        if make is None:
            continue
        best, part = math.inf, math.inf
        for _ in range(repeat):
            src = make()
            t = time.perf_counter()
            psf_map(src, geom, depth)
            best = min(best, time.perf_counter() - t)
            part = min(part, getattr(src, "last_reconstruct_s", getattr(src, "last_network_s", 0.0)))
        out[name] = {"map_s": best, "part_s": part if name != "library" else 0.0,
                     "bins": int(src.computed.sum())}
        log(f"  {lens_id} PSF map {size[0]} x {size[1]} from {name}: {best:.3f} s"
            + ("" if name == "library" else f" ({name} part {part * 1e3:.0f} ms)"))
    return out


def _store(lens_id: str, plan: Plan, lens, log) -> BasisStore | None:
    """The shipped store of the lens; for a quick run, one built from its small recipe."""
    if plan.quick:
        lib, secs = recipe_library(lens, plan.recipe(lens_id), log=log)
        return compress(lib, plan.recipe(lens_id).rank, build_s=secs, ripple_floor=plan.recipe(lens_id).ripple_floor)
    path = shipped_store(lens_id)
    return BasisStore.load(path) if path else None


def fitting_size(lens, pitch_mm: float, size) -> tuple[int, int]:
    """``size`` (rows, columns), shrunk (even, same aspect) where its diagonal
    at ``pitch_mm`` would reach past the sensor's (the double Gauss at its
    basis pitch)."""
    h, w = size
    half_diag = pitch_mm * math.hypot(h, w) / 2.0
    if half_diag <= lens.sensor.semi_diagonal_mm * 1.001:      # the paper's 1280 x 1920 spans it, rounded
        return (h, w)
    scale = lens.sensor.semi_diagonal_mm / half_diag
    return (int(h * scale) // 2 * 2, int(w * scale) // 2 * 2)


def downstream(lens_id: str, olf, log, plan: Plan) -> dict:
    """Simulation and occlusion-aware bokeh (prescribed focus) of the synthetic
    scene through ``lens_id`` at the basis pitch with each source, against the
    same with the default traced library (image PSNR, peak 1), and each
    image's PSNR against the sharp one."""
    from dcdi_core.psf.sources import OLFLibrary
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.synthetic import synthetic_rgbd
    lens = load_lens(lens_id)
    recipe = plan.recipe(lens_id)
    pitch = recipe.settings(lens).pixel_pitch_mm
    size = fitting_size(lens, pitch, plan.image_size)
    geom = ImageGeometry.from_pixel_pitch(lens, *size, pitch)
    img, depth = synthetic_rgbd(*size, seed=0)
    store = _store(lens_id, plan, lens, log)
    k = store.kernel_size if store is not None else recipe.kernel_size
    traced, _ = traced_library(lens, replace(PSFSettings(kernel_size=k), pixel_pitch_mm=pitch), plan.default_grid,
                               log)
    sources = {"trace": traced}
    if store is not None:
        sources["basis"] = BasisLibrary(store, lens)
    if olf is not None and olf.covers(lens):
        sources["olf"] = OLFLibrary(olf, lens, pixel_pitch_mm=pitch)
    out = {"image": list(size), "lens": lens_id, "pixel_pitch_mm": pitch}
    for what in ("simulate", "bokeh"):
        res = {}
        for name, lib in sources.items():
            res[name] = timed_job(what, lens, geom, img, depth, lib)
        ref = res["trace"][0]
        out[what] = {name: {"psnr_vs_trace_db": _psnr(im, ref), "psnr_vs_sharp_db": _psnr(im, img), "seconds": s}
                     for name, (im, s) in res.items()}
        log(f"  {lens_id} {what} {size[0]} x {size[1]}: " + ", ".join(
            f"{n} {v['psnr_vs_trace_db']:.2f} dB vs trace ({v['psnr_vs_sharp_db']:.2f} vs sharp)"
            for n, v in out[what].items() if n != "trace") + f"; trace vs sharp {out[what]['trace']['psnr_vs_sharp_db']:.2f}")
    return out


# ------------------------------------------------------------------ report
def run_report(lenses=None, out="out/report", *, points: int = 32, quick: bool = False, log=print) -> int:
    """The report (module docstring) into ``out``: psf-source.md,
    psf-source.json and psf-source-error-vs-storage.png."""
    from dcdi_core.psf.sources import shipped_olf_files
    from dcdi_core.psf.olf import OmniLensField
    out = Path(out)
    lenses = list(lenses or LENSES)
    olf_files = shipped_olf_files()
    olf = OmniLensField.load(olf_files[0]) if olf_files else None
    plan = Plan(points=6 if quick else points, quick=quick)
    result = {"lenses": [], "maps": [], "downstream": [], "paper": PAPER_POINT, "quick": quick,
              "reference_rays": plan.reference_rays, "olf_file": olf.path if olf else None,
              "olf_megabytes": Path(olf.path).stat().st_size / 1e6 if olf else None}
    for lid in lenses:
        log(f"report psf-source: {lid}")
        result["lenses"].append(lens_rows(lid, plan, out, log, olf))
    for lid in lenses:
        result["maps"].append(map_times(lid, olf, log, plan))
        result["downstream"].append(downstream(lid, olf, log, plan))
    result["shipped_megabytes"] = {p.name: p.stat().st_size / 1e6 for p in _shipped_files()}
    write_report(out, "psf-source", result, markdown(result), plot, log)
    return 0


def _shipped_files() -> list[Path]:
    from dcdi_core.psf.sources import shipped_olf_files
    from dcdi_core.psf.basis import STORE_DIR
    return sorted(STORE_DIR.glob("*.npz")) + list(shipped_olf_files())


def markdown(result: dict) -> str:
    lines = ["# PSF sources: error against storage and time", "",
             f"Off-grid: points uniform in field and diopters (a tenth at infinity), against kernels traced with "
             f"{result['reference_rays']} rays per pupil side; PSNR on the paper's scale (each channel over its "
             "peak), 8-bit and float, mean (worst). Grid: a random 1 % of each source's own grid against the "
             "kernels it was built from (the paper's protocol). MB: the compressed .npz (the OLF's file holds "
             "all its lenses).", ""]
    for L in result["lenses"]:
        lines += [f"## {L['lens']} ({L['pixel_pitch_mm'] * 1000:.4g} um pixels, {L['points']} points, "
                  f"reference {L['kernel_reference']} px)", "",
                  "| source | MB | build min (2 cores) | off-grid PSNR 8-bit dB | float dB | SSIM | rel. L1 | grid 1 % 8-bit dB "
                  "| grid float dB |", "|---|---|---|---|---|---|---|---|---|"]
        for r in L["rows"]:
            o, g = r["offgrid"], r["grid"]
            gs = (f"{g['psnr_8bit']:.2f} ({g['psnr_8bit_worst']:.2f}) | {g['psnr_float']:.2f}" if g else "(is the grid) |")
            name = r["name"] + (" **shipped**" if r.get("shipped") else "")
            lines.append(f"| {name} | {r['megabytes']:.2f} | {r['build_minutes']:.1f} | {o['psnr_8bit']:.2f} "
                         f"({o['psnr_8bit_worst']:.2f}) | {o['psnr_float']:.2f} ({o['psnr_float_worst']:.2f}) | "
                         f"{o['ssim_8bit']:.4f} | {o['rel_l1']:.4f} | {gs} |")
        lines.append("")
    lines += ["## PSF map time", "", "| lens | image | library in memory s | basis s (its part ms) | OLF s (network ms) |",
              "|---|---|---|---|---|"]
    for m in result["maps"]:
        def cell(key):
            v = m.get(key)
            return "n/a" if v is None else f"{v['map_s']:.3f} ({v['part_s'] * 1e3:.0f})"
        lines.append(f"| {m['lens']} | {m['image'][0]} x {m['image'][1]} | {m['library']['map_s']:.3f} | "
                     f"{cell('basis')} | {cell('olf')} |")
    lines += ["", "## Downstream: the synthetic scene with each source against traced PSFs", "",
              "| lens | image | job | source | PSNR vs traced dB | PSNR vs sharp dB (traced: ) |", "|---|---|---|---|---|---|"]
    for d in result["downstream"]:
        for what in ("simulate", "bokeh"):
            tr = d[what]["trace"]["psnr_vs_sharp_db"]
            for name, v in d[what].items():
                if name == "trace":
                    continue
                lines.append(f"| {d['lens']} | {d['image'][0]} x {d['image'][1]} | {what} | {name} | "
                             f"{v['psnr_vs_trace_db']:.2f} | {v['psnr_vs_sharp_db']:.2f} (traced {tr:.2f}) |")
    lines += ["", "Shipped PSF files: " + ", ".join(f"{k} {v:.2f} MB" for k, v in result["shipped_megabytes"].items())
              + f"; together {sum(result['shipped_megabytes'].values()):.2f} MB", ""]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9.5, 4.5))
    marks = {"basis": "o", "library": "s", "trace": "^", "olf": "D"}
    for i, L in enumerate(result["lenses"]):
        colour = f"C{i}"
        basis = [r for r in L["rows"] if r["kind"] == "basis" and r["dtype"] == "float16"]
        ax.plot([r["megabytes"] for r in basis], [r["offgrid"]["psnr_8bit"] for r in basis], "-o", color=colour,
                label=f"{L['lens']} basis (ranks {basis[0]['rank']}-{basis[-1]['rank']})")
        for r in L["rows"]:
            if r["kind"] != "basis":
                ax.plot(r["megabytes"], r["offgrid"]["psnr_8bit"], marks[r["kind"]], color=colour, mfc="none")
    for kind, name in (("library", "library uncompressed"), ("trace", "default trace (64 rays)"), ("olf", "shipped OLF")):
        ax.plot([], [], marks[kind], color="k", mfc="none", label=name)
    p = result["paper"]
    ax.plot(p["megabytes"], p["psnr_8bit"], "*", color="k", ms=12, label=p["label"])
    ax.axhline(p["psnr_8bit"], color="0.7", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_xlabel("storage, MB (compressed .npz)")
    ax.set_ylabel("off-grid PSNR, paper's scale, 8-bit (dB)")
    ax.set_title("PSF sources: off-grid error against storage")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.subplots_adjust(left=0.08, right=0.72)
    ax.grid(alpha=0.3)
    save_figure(fig, path)
    plt.close(fig)
