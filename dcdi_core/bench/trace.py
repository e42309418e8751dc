"""`dcdi bench trace` and `dcdi bench psflib`: the ray tracer (beside Optiland
0.6.3 with ``--optiland``) and the PSF library's build, each beside a simple
baseline timed in the same process."""
from __future__ import annotations

import math
import os
import time
import warnings

import numpy as np

from .timing import _best


def bench_trace(n_rays: int, repeat: int, optiland=None) -> int:
    """Trace n_rays through the double Gauss (11 surfaces + sensor), field 0.7, depth 2 m,
    at 3 wavelengths; float64 and float32; baseline: the same kernel, unchunked, one thread. With
    ``optiland`` (the python of an Optiland 0.6.3 environment) the MOS-S1 spot work beside
    Optiland's (:func:`bench_trace_optiland`)."""
    from ..optics import trace as T
    from ..optics.aiming import pupil_rays, sources, stop_grid
    from ..optics.lens import load_lens

    lens = load_lens("double-gauss")
    side = int(round(math.sqrt(n_rays / 3 * 4 / math.pi)))
    aimed = sources(lens, [2.0], field=[0.7])
    o, d, status, _ = pupil_rays(lens, aimed, stop_grid(lens, side))
    wl = np.array([486.13, 587.56, 656.27])
    o, d, status = o[0, 0, None], d[0, 0, None], status[0, 0, None]
    wls = wl[:, None]
    n = o.shape[1] * wl.size
    n_int = n * (len(lens.surfaces) + 1)
    print(f"bench trace: lens double-gauss, {len(lens.surfaces)} surfaces + sensor, "
          f"{n:,} rays ({n_int:,} ray-surface intersections), {os.cpu_count()} CPU(s), best of {repeat}")

    def run(dtype, chunk=None):
        return T.trace(lens, o, d, wls, dtype=dtype, status=status, chunk=chunk)

    results = {}
    for name, dtype in (("float64", np.float64), ("float32", np.float32)):
        t, b = _best(lambda: run(dtype), repeat)
        results[name] = (t, b)
        print(f"  {name}: {t * 1e3:8.1f} ms  {n_int / t / 1e6:7.1f} M ray-surface/s  "
              f"{n / t / 1e6:6.2f} M rays/s")
    # baseline: one chunk, no thread pool (plain vectorised numpy)
    tb, _ = _best(lambda: run(np.float64, chunk=n + 1), repeat)
    print(f"  baseline float64 (unchunked, 1 thread): {tb * 1e3:8.1f} ms  "
          f"{n_int / tb / 1e6:7.1f} M ray-surface/s")
    print(f"  speed-up over baseline: float64 x{tb / results['float64'][0]:.2f}, "
          f"float32 x{tb / results['float32'][0]:.2f}")
    b64, b32 = results["float64"][1], results["float32"][1]
    both = b64.valid & b32.valid
    diff = np.abs(b64.position_mm[..., :2] - b32.position_mm[..., :2].astype(np.float64))[both]
    print(f"  float32 vs float64 on the sensor: max |dx,dy| = {diff.max() * 1e3:.4f} um, "
          f"rms = {np.sqrt((diff ** 2).mean()) * 1e3:.4f} um; "
          f"status disagreements: {int((b64.status != b32.status).sum())} of {n:,}")
    if optiland is None:
        print("  beside Optiland 0.6.3 (same spot work, goal dcdi >= 4x): python build.py bench trace, or "
              "--optiland PYTHON (an interpreter with optiland==0.6.3)")
        return 0
    return bench_trace_optiland(n_rays, repeat, optiland)


# `dcdi bench trace --optiland`: dcdi's spot work at least this many times Optiland 0.6.3's speed
TRACE_GOAL = 4.0


def check_optiland(python) -> None:
    """Refuse an --optiland interpreter that is not there (before any work)."""
    from ..errors import InputRangeError
    if not (os.path.isfile(python) and os.access(python, os.X_OK)):
        raise InputRangeError("--optiland", str(python), "an existing Python interpreter with optiland==0.6.3 "
                                                         "(python build.py bench trace makes .venv-optiland/)")


def optiland_spec(lens, aimed, wavelength_nm: float, side: int, repeat: int = 1) -> dict:
    """The spec of optiland_spot.py for ``lens``'s spot work: its surfaces
    (mm) with our material model's indices at ``wavelength_nm`` as constant
    indices, the object distance (mm, object plane to the first vertex, as
    our depths) and object heights (mm) of the sources ``aimed`` (one
    depth), the stop grid's side and the timed repeats."""
    if any(s.aspheric_coefficients or s.odd_aspheric_coefficients for s in lens.surfaces):
        raise ValueError(f"lens {lens.id}: optiland_spot.py takes spheres and conics only")
    if aimed.depth_mm.shape[1] != 1 or not aimed.ok.all():
        raise ValueError("one depth, every field's chief ray aimed")
    n = lens.refractive_indices([wavelength_nm])[:, 0]
    z_obj = aimed.depth_mm[:, 0]
    return {"surfaces": [{"radius_mm": None if math.isinf(s.radius_mm) else s.radius_mm, "conic": s.conic,
                          "thickness_mm": s.thickness_mm, "semi_diameter_mm": s.semi_diameter_mm,
                          "index": float(n[i + 1])} for i, s in enumerate(lens.surfaces)],
            "stop_index": lens.stop_index, "object_distance_mm": float(z_obj[0]), "object_index": float(n[0]),
            # launch()'s object point: y = -p (depth + z_EP), so that the image lands at +y
            "field_heights_mm": (-aimed.p[:, 0] * (z_obj + aimed.z_ep)).tolist(),
            "wavelength_nm": float(wavelength_nm), "pupil_samples": side, "repeat": repeat}


def _spot(pos, ok) -> tuple[float, float, float]:
    """Centroid x, y and RMS radius about it (mm) of one spot's valid rays."""
    x, y = pos[ok, 0], pos[ok, 1]
    cx, cy = x.mean(), y.mean()
    return float(cx), float(cy), float(np.sqrt(np.mean((x - cx) ** 2 + (y - cy) ** 2)))


def bench_trace_optiland(n_rays: int, repeat: int, python) -> int:
    """dcdi beside Optiland 0.6.3 (``python``: its interpreter) on the same
    spot work: MOS-S1, object at 2 m, fields 0 and 0.7, the design wavelength
    (Optiland traces one wavelength per call), about n_rays rays on a square
    grid over the stop (the same points); each side aims and traces (dcdi:
    pupil_rays + trace; Optiland: Optic.trace, paraxial aiming, which is
    exact for a stop in front, record=False), float64. Runs alternated, best
    of ``repeat``; each Optiland run is a process of its own (numba warm-up
    untimed). The spots (centroid, RMS radius) show the work is the same."""
    import json
    import subprocess
    from pathlib import Path

    from ..optics import trace as T
    from ..optics.aiming import pupil_rays, sources, stop_grid
    from ..optics.lens import load_lens

    lens = load_lens("mos-s1")
    wl, fields = lens.wavelength_nm, [0.0, 0.7]
    side = max(1, int(round(math.sqrt(n_rays / len(fields) * 4 / math.pi))))
    aimed = sources(lens, [2.0], field=fields, wavelength_nm=wl)
    targets = stop_grid(lens, side)
    spec = json.dumps(optiland_spec(lens, aimed, wl, side))
    script = str(Path(__file__).with_name("optiland_spot.py"))

    def ours():
        o, d, st, _ = pupil_rays(lens, aimed, targets, wl)
        return T.trace(lens, o, d, wl, status=st)

    def theirs():
        p = subprocess.run([str(python), script], input=spec, capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"{python} {script} failed: {p.stderr[-800:]}")
        return json.loads(p.stdout)

    ours()                                           # warms the thread pool
    t_ours, t_theirs = math.inf, math.inf
    for _ in range(repeat):                          # alternated: the load changes both alike
        t, b = _best(ours, 1)
        t_ours = min(t_ours, t)
        r = theirs()
        t_theirs = min(t_theirs, r["seconds"])
    n_ours, n_theirs = b.status.size, r["rays"]
    print(f"bench trace beside Optiland 0.6.3: mos-s1 ({len(lens.surfaces)} surfaces + sensor), object at 2 m, "
          f"fields {fields[0]:g} and {fields[1]:g}, {wl:g} nm, a {side}^2 grid over the stop, float64, aiming + "
          f"trace, {os.cpu_count()} CPU(s), best of {repeat}, runs alternated")
    for name, t, n in (("dcdi", t_ours, n_ours), ("Optiland 0.6.3", t_theirs, n_theirs)):
        print(f"  {name:15s} {t * 1e3:8.1f} ms  {n:,} rays  {n / t / 1e6:6.2f} M rays/s")
    ratio = (n_ours / t_ours) / (n_theirs / t_theirs)
    print(f"  dcdi / Optiland (rays/s): x{ratio:.2f}  goal >= {TRACE_GOAL:.1f}x: "
          f"{'met' if ratio >= TRACE_GOAL else 'NOT met'}; load average {os.getloadavg()[0]:.2f}")
    pos, valid = b.position_mm[:, 0], b.valid[:, 0]
    for i, f in enumerate(fields):
        cx, cy, rms = _spot(pos[i], valid[i])
        s = r["spots"][i]
        dc = math.hypot(cx - s["centroid_mm"][0], cy - s["centroid_mm"][1])
        print(f"  spot at field {f:g}: RMS radius {rms * 1e3:.4f} um (Optiland {s['rms_radius_mm'] * 1e3:.4f}), "
              f"centroid ({cx:.6f}, {cy:.6f}) mm (Optiland ({s['centroid_mm'][0]:.6f}, {s['centroid_mm'][1]:.6f})); "
              f"differ by {abs(rms - s['rms_radius_mm']) * 1e3:.2g} and {dc * 1e3:.2g} um; "
              f"rays reaching the sensor {int(valid[i].sum()):,} ({s['valid']:,})")
    return 0


def bench_psflib(quick: bool = False) -> int:
    """MOS-S1: 64 fields x 20 depth bins (19 finite + infinity), RGB, no cache;
    first the issue's workload (9 wavelengths x 128^2 rays), then the library
    defaults. Baseline: the simple way, one PSF at a time with an unchunked
    single-thread float64 trace and a per-ray np.add.at deposit of the
    pixel-integrated Gaussian, timed on 3 PSFs in the same process."""
    from ..optics.lens import load_lens
    from ..psf.compute import PSFSettings
    from ..psf.library import LibraryGrid

    lens = load_lens("mos-s1")
    grid = LibraryGrid(n_fields=8 if quick else 64, n_depths=2 if quick else 19)
    workload = PSFSettings(pupil_samples=128, n_wavelengths=9)
    per_psf = _bench_library(lens, workload, grid)
    _bench_library(lens, PSFSettings(), grid)
    _bench_baseline(lens, workload, grid, per_psf)
    _bench_footprint(quick)
    return 0


def _bench_footprint(quick: bool) -> None:
    """Wide kernels, each ray over its footprint against the histogram alone
    (the deposit before; the baseline, in the same process): the Sonnar
    focused at 1.5 m, lights at 10 m across the field (a 120-140 px blur at
    8 um), 96 rays a side, 9 wavelengths; and how much each changes when the
    rays double (PSNR against the kernel's peak, the mean over the fields)."""
    from ..optics.aiming import sources
    from ..optics.lens import load_lens
    from ..psf import deposit
    from ..psf.compute import PSFSettings, compute_sources, focused_lens, spectral_samples

    lens = load_lens("zeiss-sonnar-50mm-f1-5")
    n = 2 if quick else 8
    rows = {}
    for name, min_px in (("footprint", deposit.FOOTPRINT_MIN_PX), ("histogram (baseline)", math.inf)):
        saved, deposit.FOOTPRINT_MIN_PX = deposit.FOOTPRINT_MIN_PX, min_px
        try:
            kernels = {}
            for rays in (96, 192):
                s = PSFSettings(kernel_size=181, pupil_samples=rays, n_wavelengths=9, pixel_pitch_mm=0.008,
                                focus_distance_m=1.5)
                wl, w = spectral_samples(s, None)
                aimed = sources(focused_lens(lens, s), np.full(n, 10.0), field=np.linspace(0.0, 0.9, n))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    b = compute_sources(lens, aimed, s, wl, w)
                kernels[rays] = (b.psf.astype(np.float64), b.timings_s["deposit"], sum(b.timings_s.values()))
        finally:
            deposit.FOOTPRINT_MIN_PX = saved
        (k1, t1, all1), (k2, _, _) = kernels[96], kernels[192]
        db = [10.0 * math.log10(k2[i].max() ** 2 / np.mean((k2[i] - k1[i]) ** 2)) for i in range(n)]
        rows[name] = (t1, all1, float(np.mean(db)), float(np.min(db)))
    base, base_all = rows["histogram (baseline)"][:2]
    print(f"bench psflib: wide kernels, zeiss-sonnar-50mm-f1-5 focused at 1.5 m, {n} lights at 10 m (fields 0-0.9), "
          "181 px at 8 um, 96 rays a side, 9 wavelengths")
    for name, (t, whole, mean_db, worst_db) in rows.items():
        print(f"  {name}: deposit {t:.2f} s ({t / base:.2f} x the baseline's), the PSFs {whole:.2f} s "
              f"({whole / base_all:.2f} x); 96 -> 192 rays change {mean_db:.1f} dB mean, {worst_db:.1f} dB worst "
              "(PSNR against the kernel's peak)")


def _bench_library(lens, settings, grid):
    from ..outputs import scratch_folder

    from ..optics.aiming import stop_grid
    from ..psf.compute import spectral_samples
    from ..progress import psf_progress
    from ..psf.library import PSFLibrary

    n_psf = grid.n_fields * (grid.n_depths + 1)
    n_p = len(stop_grid(lens, settings.pupil_samples))
    wl, w = spectral_samples(settings, None)
    n_rays = n_psf * n_p * wl.size
    print(f"bench psflib: mos-s1, {grid.n_fields} fields x {grid.n_depths + 1} depth bins = {n_psf} RGB PSFs "
          f"{settings.kernel_size}x{settings.kernel_size}, {wl.size} wavelengths x {n_p:,} rays in the stop "
          f"({settings.pupil_samples}^2 grid, {settings.precision}) = {n_rays:,} rays, {os.cpu_count()} CPU(s)")
    lib = PSFLibrary(lens, settings, grid, None)
    t = time.perf_counter()
    lib.build(progress=psf_progress("  building"))
    total = time.perf_counter() - t
    with scratch_folder() as d:
        t = time.perf_counter()
        lib.save(os.path.join(d, "lib.npz"))
        io_s = time.perf_counter() - t
    tm = lib.last_timings_s
    other = total - tm["aim"] - tm["trace"] - tm["deposit"]
    print(f"  total {total:.1f} s = {n_rays / total / 1e6:.2f} M rays/s "
          f"({n_rays * (len(lens.surfaces) + 1) / total / 1e6:.1f} M ray-surface/s)")
    print(f"  where the time goes: aim {tm['aim']:.1f} s, trace {tm['trace']:.1f} s, "
          f"deposit {tm['deposit']:.1f} s, other {other:.1f} s; writing the file (I/O) {io_s:.2f} s")
    return total / n_psf


def _bench_baseline(lens, settings, grid, per: float) -> None:
    """The simple way, timed on 3 PSFs: see bench_psflib."""
    from ..optics import trace as T
    from ..optics.aiming import Aimed, launch, pupil_rays, sources, stop_grid
    from ..psf.compute import pixel_pitch_mm, spectral_samples
    from ..psf.deposit import gaussian_sigma_px

    wl, w = spectral_samples(settings, None)
    n_psf = grid.n_fields * (grid.n_depths + 1)
    pitch = pixel_pitch_mm(lens, settings)
    k = settings.kernel_size
    sig = gaussian_sigma_px()
    import math as _m
    erf = np.vectorize(_m.erf)
    aimed = sources(lens, [2.0], field=[0.3, 0.6, 0.9])
    whole = 1 << 30                               # one chunk: unchunked, on this thread
    t = time.perf_counter()
    for i in range(aimed.p.shape[0]):
        a = Aimed(aimed.depth_mm[i], aimed.p[i], aimed.v_chief[i], aimed.ok[i], aimed.z_ep)
        o, dd, st, _ = pupil_rays(lens, a, stop_grid(lens, settings.pupil_samples))
        oc, dc = launch(lens, a.depth_mm, a.p, 0.0, a.v_chief, a.z_ep)
        cy = T.trace(lens, oc, dc, lens.wavelength_nm, apertures=False, chunk=whole).position_mm[0, 1]
        kern = np.zeros((3, k, k))
        for j, lam in enumerate(wl):
            b = T.trace(lens, o, dd, lam, status=st, chunk=whole)
            v = b.valid[0]
            x = b.position_mm[0, v, 0] / pitch + k / 2
            y = (b.position_mm[0, v, 1] - cy) / pitch + k / 2
            ix0, iy0 = np.floor(x).astype(int) - 2, np.floor(y).astype(int) - 2
            for dx_ in range(5):
                gx = erf((ix0 + dx_ + 1 - x) / (sig * _m.sqrt(2))) - erf((ix0 + dx_ - x) / (sig * _m.sqrt(2)))
                for dy_ in range(5):
                    gy = erf((iy0 + dy_ + 1 - y) / (sig * _m.sqrt(2))) - erf((iy0 + dy_ - y) / (sig * _m.sqrt(2)))
                    ii, jj = iy0 + dy_, ix0 + dx_
                    ok = (ii >= 0) & (ii < k) & (jj >= 0) & (jj < k)
                    for c in range(3):
                        np.add.at(kern[c], (ii[ok], jj[ok]), 0.25 * gx[ok] * gy[ok] * w[j, c])
    per_base = (time.perf_counter() - t) / aimed.p.shape[0]
    print(f"baseline (one PSF at a time, float64, 1 thread, np.add.at deposit; 128^2 rays, 9 wavelengths): "
          f"{per_base * 1e3:.0f} ms/PSF vs {per * 1e3:.1f} ms/PSF for the same workload above: "
          f"x{per_base / per:.1f}; the baseline would take {per_base * n_psf:.0f} s for this library")


