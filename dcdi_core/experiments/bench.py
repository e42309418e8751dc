"""`dcdi bench`: timings printed, never asserted.

Each benchmark times the real code path and a simple baseline in the same
process and prints the ratio, so that figures from different machines compare.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np


def _best(fn, repeat):
    best = math.inf
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


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
    return 0


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


def bench_render(quick: bool = False) -> int:
    """1280 x 1920 RGB (the synthetic scene), 16-px patches, 41 x 41 PSFs:
    MOS-S1 simulation and 6P bokeh, PSF libraries built beforehand (cached);
    baseline: direct per-patch spatial convolution, timed on a sample of
    patches in the same run and scaled to the image."""
    import tracemalloc

    from ..optics.lens import load_lens
    from ..render.convolve import ConvolveOptions, patch_convolve
    from ..render.geometry import ImageGeometry
    from ..render.psfmap import psf_map
    from ..render.bokeh import BokehOptions, bokeh
    from ..render.simulate import SimulateOptions, open_library, simulate
    from ..render.synthetic import synthetic_rgbd

    h, w = (320, 480) if quick else (1280, 1920)
    m = 16
    img, depth = synthetic_rgbd(h, w, seed=0)
    mos, p6 = load_lens("mos-s1"), load_lens("6p")
    geom = ImageGeometry.full_sensor(mos, h, w)
    print(f"bench render: {h} x {w} RGB, {m}-px patches, 41 x 41 PSFs, {os.cpu_count()} CPU(s)")
    t = time.perf_counter()
    lib = open_library(mos, geom)
    lib.ensure(depth, clamp_near=True)
    lib6 = open_library(p6, ImageGeometry.full_sensor(p6, h, w))
    lib6.ensure(depth, clamp_near=True)
    print(f"  PSF libraries for this scene (built or read from the cache, not in the times below): "
          f"{time.perf_counter() - t:.1f} s")
    rep = 1 if quick else 2                    # best of rep: the first call also warms the thread pool
    t_map, pm = _best(lambda: psf_map(lib, geom, depth, m), rep)
    t_conv, _ = _best(lambda: patch_convolve(img, pm.kernels, m, identity=pm.identity), rep)
    t_sim, _ = _best(lambda: simulate(img, depth, mos, SimulateOptions(geometry=geom, distortion=False),
                                      library=lib), rep)
    t_sim_d, _ = _best(lambda: simulate(img, depth, mos, SimulateOptions(geometry=geom), library=lib), rep)
    from ..render import fft
    # the fallback that Blender's Python gets
    t_sim_np, _ = _best(lambda: simulate(img, depth, mos, SimulateOptions(geometry=geom, distortion=False,
                                                                          fft_backend="numpy"), library=lib), 1)
    plain, layered = BokehOptions(keep=(1.1, 1.3), occlusion=False), BokehOptions(keep=(1.1, 1.3), occlusion=True)
    t_bk_plain, _ = _best(lambda: bokeh(img, depth, p6, plain, library=lib6), rep)
    t_bk, _ = _best(lambda: bokeh(img, depth, p6, layered, library=lib6), rep)
    # the low-rank method (ConvolveOptions(method='lowrank')), alternated with the default in this process
    eps_lr = 0.005
    lowrank = ConvolveOptions(method="lowrank", rank_eps=eps_lr)
    t_conv_lr, t_bk_lr, t_bk_plain_lr = math.inf, math.inf, math.inf
    for _ in range(rep):
        t_conv_lr = min(t_conv_lr, _best(lambda: patch_convolve(img, pm.kernels, m, lowrank, identity=pm.identity),
                                         1)[0])
        t_conv = min(t_conv, _best(lambda: patch_convolve(img, pm.kernels, m, identity=pm.identity), 1)[0])
    plain_lr = dataclasses.replace(plain, convolution="lowrank", rank_eps=eps_lr)
    layered_lr = dataclasses.replace(layered, convolution="lowrank", rank_eps=eps_lr)
    t_bk_plain_lr, _ = _best(lambda: bokeh(img, depth, p6, plain_lr, library=lib6), rep)
    t_bk_lr, _ = _best(lambda: bokeh(img, depth, p6, layered_lr, library=lib6), rep)
    tracemalloc.start()
    patch_convolve(img, pm.kernels, m, lowrank, identity=pm.identity)
    peak_lr = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    patch_convolve(img, pm.kernels, m, identity=pm.identity)
    peak_win = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # peak memory in separate runs (tracing slows numpy's allocations a little)
    tracemalloc.start()
    simulate(img, depth, mos, SimulateOptions(geometry=geom), library=lib)
    peak_sim = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    bokeh(img, depth, p6, layered, library=lib6)
    peak_bk = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"  simulation: {t_sim:.2f} s (PSF map {t_map:.2f} s + convolution {t_conv:.2f} s, "
          f"{fft.backend()} FFT); with distortion {t_sim_d:.2f} s (peak memory {peak_sim / 2**20:.0f} MiB); "
          f"with numpy's float64 FFT (no scipy, as in Blender) {t_sim_np:.2f} s")
    print(f"  bokeh (6P, keep 1.1-1.3 m): occlusion-aware {t_bk:.2f} s, plain {t_bk_plain:.2f} s; "
          f"peak memory {peak_bk / 2**20:.0f} MiB")
    print(f"  low-rank tiles (8 x 8 patches, rank eps {eps_lr:g}): simulation's convolution {t_conv_lr:.2f} s "
          f"against {t_conv:.2f} s (x{t_conv / t_conv_lr:.2f}; peak memory {peak_lr / 2**20:.0f} against "
          f"{peak_win / 2**20:.0f} MiB); bokeh occlusion-aware {t_bk_lr:.2f} s (x{t_bk / t_bk_lr:.2f}), plain "
          f"{t_bk_plain_lr:.2f} s (x{t_bk_plain / t_bk_plain_lr:.2f}); load average {os.getloadavg()[0]:.1f}")
    _bench_bokeh_multires(img, depth, p6, lib6, quick, rep)
    # baseline: each patch's output by direct spatial convolution of its padded input
    k = pm.kernels.shape[-1]
    r = k // 2
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="reflect")
    rng = np.random.default_rng(0)
    nph, npw = pm.kernels.shape[:2]
    sample = rng.choice(nph * npw, size=min(24, nph * npw), replace=False)
    t = time.perf_counter()
    for idx in sample:
        i, j = divmod(int(idx), npw)
        tile = pad[i * m:i * m + m + 2 * r, j * m:j * m + m + 2 * r]
        kern = pm.kernels[i, j]
        out = np.zeros((min(m, tile.shape[0] - 2 * r), min(m, tile.shape[1] - 2 * r), 3), np.float32)
        for dy in range(k):
            for dx in range(k):
                out += kern[:, dy, dx] * tile[2 * r - dy:2 * r - dy + out.shape[0], 2 * r - dx:2 * r - dx + out.shape[1]]
    per_patch = (time.perf_counter() - t) / len(sample)
    t_base = per_patch * nph * npw
    print(f"  baseline (direct per-patch convolution, {len(sample)} patches timed): {per_patch * 1e3:.1f} ms/patch "
          f"-> {t_base:.1f} s for the image; simulation is x{t_base / t_sim:.1f} faster")
    _bench_simulation_paths(img, depth, mos, geom, lib, rep)
    if not quick:
        print("  the speed goals, as whole processes (`dcdi bench cli`'s goal rows):")
        goal_rows(repeat=rep)
    return 0


def _bench_simulation_paths(img, depth, lens, geom, lib, rep: int) -> dict:
    """The simulation's paths (issue 15) against the exact one, in this
    process, runs alternated (best of ``rep``): the exact path
    (``convolution='windows'``, the former PSF-map layout), the default
    ('fast', scipy's float32 FFT when installed), the numpy-only path
    Blender gets (``fft_backend='numpy'``, the exact path beside it), and
    torch (``accelerator='torch'``) where it imports. Peak memory: numpy's
    allocations by tracemalloc (one run each); torch's are invisible to it,
    so for torch the process's peak RSS (resource.getrusage) after its runs
    is printed instead, which includes everything before it. CPU seconds
    (all threads, time.process_time) beside wall seconds: on shared cores
    they move less with the load."""
    import resource
    import tracemalloc

    from ..render import accel_torch
    from ..render.simulate import SimulateOptions, simulate

    cases = {"exact": dict(convolution="windows"), "default": {},
             "exact, numpy FFT": dict(convolution="windows", fft_backend="numpy"),
             "numpy-only": dict(fft_backend="numpy"), "default, blend 6": dict(blend=6)}
    if accel_torch.available():
        cases["torch"] = dict(accelerator="torch")
        cases["torch, 1 thread"] = dict(accelerator="torch", torch_threads=1)

    def run(kw):
        kw = dict(kw)
        threads = kw.pop("torch_threads", None)
        if threads is None:
            return simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, **kw), library=lib).image
        import torch
        before = torch.get_num_threads()
        torch.set_num_threads(threads)         # this process's setting, restored at once
        try:
            return simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, **kw), library=lib).image
        finally:
            torch.set_num_threads(before)

    best = {name: math.inf for name in cases}
    cpu = {name: math.inf for name in cases}
    out = {}
    for _ in range(max(rep, 1)):
        for name, kw in cases.items():
            c = time.process_time()
            t, out[name] = _best(lambda: run(kw), 1)
            best[name] = min(best[name], t)
            cpu[name] = min(cpu[name], time.process_time() - c)
    peak = {}
    for name, kw in cases.items():
        if name.startswith("torch"):
            continue
        tracemalloc.start()
        run(kw)
        peak[name] = tracemalloc.get_traced_memory()[1] / 2 ** 20
        tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    threads = ""
    if accel_torch.available():
        import torch
        threads = f"; torch {torch.get_num_threads()} intra-op threads by default"
    print(f"  simulation paths (issue 15; MOS-S1, no distortion, best of {max(rep, 1)}, alternated; "
          f"load average {os.getloadavg()[0]:.1f}{threads}):")
    for name in cases:
        ref = "exact, numpy FFT" if name == "numpy-only" else "exact"
        diff = float(np.abs(out[name] - out[ref]).max())
        mem = (f"peak memory {peak[name]:.0f} MiB (tracemalloc)" if name in peak else
               f"process peak RSS {rss:.0f} MiB (getrusage, whole run so far)")
        print(f"    {name:<17} {best[name]:6.2f} s ({cpu[name]:5.2f} CPU s)  x{best[ref] / best[name]:.2f} "
              f"(CPU x{cpu[ref] / cpu[name]:.2f}) against {ref}, max |diff| {diff:.1e}; {mem}")
    if img.shape[:2] != (1280, 1920):
        return best
    print(f"  goal: simulation <= 1.0 s (default {best['default']:.2f} s: "
          f"{'met' if best['default'] <= 1.0 else 'NOT met'}), numpy-only <= 2.0 s "
          f"({best['numpy-only']:.2f} s: {'met' if best['numpy-only'] <= 2.0 else 'NOT met'})")
    return best


def bench_simulation_paths(quick: bool = False) -> int:
    """Only the simulation-paths block of ``bench_render`` (same scene, lens
    and library): ``python -c "from dcdi_core.experiments.bench import
    bench_simulation_paths as b; b()"``."""
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    from ..render.simulate import open_library
    from ..render.synthetic import synthetic_rgbd

    h, w = (320, 480) if quick else (1280, 1920)
    img, depth = synthetic_rgbd(h, w, seed=0)
    lens = load_lens("mos-s1")
    geom = ImageGeometry.full_sensor(lens, h, w)
    lib = open_library(lens, geom)
    lib.ensure(depth, clamp_near=True)
    print(f"bench simulation paths: {h} x {w} RGB, 16-px patches, {lib.kernel_size} x {lib.kernel_size} PSFs, "
          f"{os.cpu_count()} CPU(s)")
    _bench_simulation_paths(img, depth, lens, geom, lib, 1 if quick else 2)
    return 0


# ---- multi-resolution bokeh (issue 15): kept in one block, called from bench_render
def _bench_bokeh_multires(img, depth, lens, lib41, quick: bool, rep: int) -> None:
    """The multi-resolution bokeh (``BokehOptions(multires=c)``) against the exact
    path, alternated in this process, occlusion-aware and plain, with the
    41 px library above and with the fitted kernels ``bokeh()`` opens by
    default; PSNR and max abs difference against the exact result; peak
    memory (tracemalloc) of each."""
    import tracemalloc

    from .simulation_accuracy import psnr
    from ..render.geometry import ImageGeometry
    from ..render.multires import BENCH_C, DEFAULT_MAX_LEVEL
    from ..render.bokeh import BokehOptions, bokeh
    from ..render.simulate import open_library

    h, w = depth.shape
    fitted = open_library(lens, ImageGeometry.full_sensor(lens, h, w), fit_depth_m=depth)
    peak = float(img.max())
    for lib in (lib41, fitted):
        for occ in (True, False):
            def run(c):
                opts = BokehOptions(keep=(1.1, 1.3), occlusion=occ, multires=c)
                return bokeh(img, depth, lens, opts, library=lib).image
            t_ex, t_mr = math.inf, math.inf
            for _ in range(rep):                     # alternated: the load changes both alike
                t, exact = _best(lambda: run(None), 1)
                t_ex = min(t_ex, t)
                t, res = _best(lambda: run(BENCH_C), 1)
                t_mr = min(t_mr, t)
            tracemalloc.start()
            run(None)
            peak_ex = tracemalloc.get_traced_memory()[1]
            tracemalloc.reset_peak()
            run(BENCH_C)
            peak_mr = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            print(f"  multi-resolution bokeh (c {BENCH_C:g} px, max level {DEFAULT_MAX_LEVEL}), "
                  f"{lib.kernel_size} px kernels, {'occlusion-aware' if occ else 'plain'}: {t_mr:.2f} s against "
                  f"exact {t_ex:.2f} s (x{t_ex / t_mr:.2f}); PSNR vs exact {psnr(res / peak, exact / peak):.2f} dB, "
                  f"max |diff| {np.abs(res - exact).max() / peak:.4f} of the peak; peak memory "
                  f"{peak_mr / 2**20:.0f} against {peak_ex / 2**20:.0f} MiB; load average {os.getloadavg()[0]:.1f}",
                  flush=True)


def bench_correction(quick: bool = False) -> int:
    """MOS-S1, the synthetic scene on the full sensor (1280 x 1920, the
    paper's 12.2 um pixels; quick: 320 x 480), the shipped OLF's PSFs (all
    bins computed beforehand) for both: the simulation that makes a capture
    (distortion, the depth-aware blur, sensor noise) against the
    deconvolution that undoes it (``correct.deconvolve``, default options;
    then with depth layers 0.1 D), alternated in this process, best of 2
    (quick: 1). Wall and CPU seconds (all threads, time.process_time); the
    goal is a deconvolution at most 2 x the simulation."""
    from ..correct import DeconvOptions, deconvolve
    from ..models.common.metrics import psnr
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    from ..render.simulate import LensSimulator, SimulateOptions
    from ..render.synthetic import synthetic_rgbd

    h, w = (320, 480) if quick else (1280, 1920)
    lens = load_lens("mos-s1")
    img, depth = synthetic_rgbd(h, w, seed=0)
    geom = ImageGeometry.full_sensor(lens, h, w)
    from ..app.sources import PSFRequest, open_source
    src = open_source(lens, geom, PSFRequest(), fit_depth_m=depth)
    lib = src.library
    lib.build()
    sim = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)
    print(f"bench correction: mos-s1, {h} x {w} RGB (synthetic scene, {geom.pixel_pitch_mm * 1000:.3g} um pixels), "
          f"{lib.kernel_size} x {lib.kernel_size} PSFs ({src.kind}), {os.cpu_count()} CPU(s), load average "
          f"{os.getloadavg()[0]:.2f}")
    noise = {"full_well_electrons": 10000.0, "read_noise_electrons": 3.0}
    cases = {"simulation": lambda: sim(img, depth, noise=noise, seed=0),
             "deconvolution": lambda: deconvolve(cap.image, cap.depth, lens, DeconvOptions(), geometry=geom,
                                                 library=lib),
             "deconvolution, layers 0.1 D": lambda: deconvolve(cap.image, cap.depth, lens,
                                                               DeconvOptions(layer_step_diopters=0.1),
                                                               geometry=geom, library=lib)}
    cap = cases["simulation"]()
    best = {k: (math.inf, math.inf) for k in cases}
    out = {}
    for _ in range(1 if quick else 2):            # alternated: the load changes all alike
        for name, fn in cases.items():
            t, c = time.perf_counter(), time.process_time()
            out[name] = fn()
            best[name] = (min(best[name][0], time.perf_counter() - t), min(best[name][1], time.process_time() - c))
    ok = np.isfinite(cap.depth)
    truth = np.clip(cap.sharp, 0, 1)[ok]
    sim_wall, sim_cpu = best["simulation"]
    for name, (wall, cpu) in best.items():
        line = f"  {name}: {wall:.2f} s wall, {cpu:.2f} s CPU"
        if name != "simulation":
            line += (f" (x{wall / sim_wall:.2f} wall, x{cpu / sim_cpu:.2f} CPU of the simulation); PSNR "
                     f"{psnr(np.clip(out[name].image, 0, 1)[ok], truth, 1.0):.2f} dB")
        else:
            line += f"; the capture's PSNR {psnr(np.clip(cap.image, 0, 1)[ok], truth, 1.0):.2f} dB"
        print(line, flush=True)
    ratio = best["deconvolution"][0] / sim_wall
    print(f"  goal: deconvolution <= 2 x the simulation (wall): {'met' if ratio <= 2.0 else 'NOT met'} "
          f"(x{ratio:.2f}); load average {os.getloadavg()[0]:.2f}")
    return 0


def bench_dacn(quick: bool = False, threads: int = 1) -> int:
    """DACN inference per configuration (untrained weights: the time does not
    depend on them): one 256^2 tile, 480 x 640 and 1280 x 1920 tiled
    (256 px tiles, 32 px overlap), the process's peak RSS after each size;
    the baseline is one untiled forward pass of the 480 x 640 image."""
    import resource

    import torch

    from ..models.dacn.arch import DACN
    from ..models.dacn.spec import named
    from ..models.dacn.correct import correct
    from ..models.runtime.conditioning import field_maps

    torch.set_num_threads(threads)
    configs = ("tiny", "refine") if quick else ("refine", "tiny", "tiny-rb", "demo")
    sizes = ((64, 96),) if quick else ((480, 640), (1280, 1920))
    rng = np.random.default_rng(0)
    print(f"DACN inference, {threads} torch thread(s), float32, tiles 256 px overlapping by 32 px; a refining "
          "network's deconvolution is not included (dcdi bench correction times it)")
    for name in configs:
        torch.manual_seed(0)
        model = DACN(named(name)).eval()
        params = sum(p.numel() for p in model.parameters())

        def run(img, dep, **kw):
            # a refining network reads a deconvolved image (the capture stands in: the time is the same) and,
            # conditioned, each pixel's field (the image centred on the MOS-S1 sensor)
            extra = {"deconvolved": img} if model.spec.refine else {}
            if model.spec.condition:
                h, w = img.shape[:2]
                extra["field"] = field_maps(((h - 1) / 2, (w - 1) / 2), 0.0122, 14.0, np.arange(h), np.arange(w))
            return correct(model, img, dep, **extra, **kw)

        tile = rng.uniform(0, 1, (256, 256, 3)).astype(np.float32)
        t_tile, _ = _best(lambda: run(tile, np.full((256, 256), 2.0)), 1 if quick else 2)
        print(f"  {name}: {params:,} parameters; one 256^2 tile {t_tile:.3f} s")
        for h, w in sizes:
            img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
            dep = rng.uniform(0.7, 10.0, (h, w))
            t, _ = _best(lambda: run(img, dep), 1)
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            line = f"    {h} x {w}: {t:.2f} s tiled, peak RSS {rss:.0f} MiB"
            if (h, w) == sizes[0]:
                t_whole, _ = _best(lambda: run(img, dep, tile=max(h, w)), 1)
                line += f"; untiled {t_whole:.2f} s (tiled / untiled {t / t_whole:.2f})"
            print(line)
    return 0


def _process(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (the child's user + system) of one whole process."""
    import resource
    import subprocess
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {p.stderr[-800:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _cli_inputs(d: str, quick: bool):
    """The bench's synthetic RGB-D written to folder ``d``: (python command, numpy-only command, image args
    of the 6P, of MOS-S1)."""
    import sys
    from ..io.images import write_depth, write_image
    from ..render.synthetic import synthetic_rgbd
    h, w = (320, 480) if quick else (1280, 1920)
    img, depth = synthetic_rgbd(h, w, seed=0)
    write_image(f"{d}/aif.exr", img)
    write_depth(f"{d}/depth.exr", depth)
    py = [sys.executable, "-m", "dcdi_core"]
    # Blender's own Python: numpy only (no scipy, no threadpoolctl)
    numpy_only = [sys.executable, "-c", "import sys, runpy; sys.modules['scipy'] = None; "
                  "sys.modules['threadpoolctl'] = None; sys.argv = ['dcdi'] + sys.argv[1:]; "
                  "runpy.run_module('dcdi_core', run_name='__main__')"]
    rgbd = ["--image", f"{d}/aif.exr", "--depth", f"{d}/depth.exr"]
    return py, numpy_only, rgbd + ["--lens", "6p"], rgbd + ["--lens", "mos-s1"]


def _goal_jobs(d: str, inputs) -> dict:
    """{row: (command, goal s)} of the rows the speed goals are set on; ``inputs``: ``_cli_inputs``'s."""
    py, numpy_only, io, mos = inputs
    keep = ["--keep", "1.0", "2.0"]
    return {"dcdi simulate --lens mos-s1": (py + ["simulate", *mos, "-o", f"{d}/sim.exr"], GOALS["simulate"]),
            "dcdi bokeh --keep 1.0 2.0": (py + ["bokeh", *io, *keep, "-o", f"{d}/b.exr"], GOALS["bokeh"]),
            "  the same, numpy only": (numpy_only + ["bokeh", *io, *keep, "-o", f"{d}/b.exr"],
                                       GOALS["bokeh, numpy only"])}


def _run_rows(jobs: dict, repeat: int, quick: bool, base: float | None = None) -> None:
    """Each job once to warm the caches, then the best of ``repeat``: one line each, its goal beside."""
    for name, (cmd, goal) in jobs.items():
        _process(cmd)
        wall, cpu = min(_process(cmd) for _ in range(repeat))
        base = base or wall
        aim = "" if goal is None or quick else f"  goal <= {goal:.1f} s: {'met' if wall <= goal else 'NOT met'}"
        print(f"  {name:36s} {wall:6.2f} s ({cpu:6.2f} s CPU)  x{wall / base:5.1f} the start-up{aim}", flush=True)


def goal_rows(repeat: int = 2) -> int:
    """The whole-process rows the speed goals are set on (1280 x 1920, warm), each beside its goal."""
    import sys
    from ..outputs import scratch_folder
    with scratch_folder() as d:
        base, _ = min(_process([sys.executable, "-m", "dcdi_core", "--help"]) for _ in range(2))
        _run_rows(_goal_jobs(d, _cli_inputs(d, False)), repeat, False, base)
    return 0


def bench_cli(quick: bool = False, repeat: int = 2) -> int:
    """The CLI's whole processes (start-up, reading, PSFs, the job, writing)
    on a synthetic RGB-D image (seed 0) of 1280 x 1920 (320 x 480 with
    --quick), the 6P lens, PSFs from the shipped OLF: `dcdi simulate` and
    `dcdi bokeh --focus 1.5`, each run once to warm the caches, then
    ``repeat`` times (best kept). Baseline: `dcdi --help` (Python and the
    CLI's own start-up)."""
    from ..outputs import scratch_folder
    h, w = (320, 480) if quick else (1280, 1920)
    print(f"whole processes on a {h} x {w} synthetic RGB-D (seed 0), 6P, {os.cpu_count()} CPU(s), "
          f"load average {os.getloadavg()[0]:.1f}; wall (CPU) seconds, best of {repeat} after a warm-up run")
    with scratch_folder() as d:
        inputs = _cli_inputs(d, quick)
        py, io = inputs[0], inputs[2]
        jobs = {"dcdi --help (start-up)": (py + ["--help"], None),
                "dcdi simulate": (py + ["simulate", *io, "-o", f"{d}/sim.exr"], None),
                "dcdi bokeh --focus 1.5": (py + ["bokeh", *io, "--focus", "1.5", "-o", f"{d}/bokeh.exr"], None),
                **_goal_jobs(d, inputs),
                "dcdi bokeh --keep 1.0 2.0 --plain": (py + ["bokeh", *io, "--keep", "1.0", "2.0", "--plain", "-o",
                                                            f"{d}/b.exr"], None)}
        _run_rows(jobs, repeat, quick)
    return 0


# whole processes at 1280 x 1920 on 2 cores, caches warm (`dcdi bench cli`)
GOALS = {"simulate": 2.0, "bokeh": 3.0, "bokeh, numpy only": 4.5}


# Linux counts a forked child's peak from its parent's size at the fork (and
# keeps it across exec): the job is started by a small helper process, so its
# peak is its own
_PEAK_HELPER = """
import os, subprocess, sys
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
_, status, usage = os.wait4(p.pid, 0)
err = p.stderr.read().decode(errors="replace")
code = os.waitstatus_to_exitcode(status)
print(usage.ru_maxrss if code == 0 else "failed " + err[-800:])
"""


def _peak_rss_bytes(cmd: list[str]) -> int:
    """The peak resident memory (bytes) of one whole process ``cmd``."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-S", "-c", _PEAK_HELPER, *cmd], capture_output=True, text=True).stdout
    if out.startswith("failed"):
        raise RuntimeError(f"{' '.join(cmd)} failed: {out[7:]}")
    return int(out) * 1024                      # Linux reports KiB


def bench_memory(quick: bool = False) -> int:
    """Peak RSS of `dcdi simulate`, `bokeh --keep 0.9 1.1` and `correct
    --method deconv` (MOS-S1, its PSF basis) on the synthetic scene at two
    sizes; their growth per pixel is what the job needs per pixel, printed
    beside ``memory.JOB_BYTES_PER_PIXEL`` (the estimate that refuses an image
    too large before it is read)."""
    import sys
    from ..outputs import scratch_folder
    from ..io.images import write_depth, write_image
    from ..memory import JOB_BYTES_PER_PIXEL, gib
    from ..render.synthetic import synthetic_rgbd
    sizes = [(160, 240), (640, 960)] if quick else [(320, 480), (1280, 1920)]
    jobs = {"simulate": ["--psf-source", "basis"], "bokeh": ["--keep", "0.9", "1.1", "--psf-source", "basis"],
            "correct": ["--method", "deconv", "--psf-source", "basis"]}
    print(f"peak RSS (wait4) of whole processes, MOS-S1 and its PSF basis, synthetic scene (seed 1) at "
          f"{sizes[0][0]} x {sizes[0][1]} and {sizes[1][0]} x {sizes[1][1]}")
    print("| job | small | large | bytes per pixel (growth) | estimate used |")
    print("|---|---|---|---|---|")
    with scratch_folder() as d:
        for h, w in sizes:
            img, depth = synthetic_rgbd(h, w, seed=1)
            write_image(f"{d}/{h}.exr", img)
            write_depth(f"{d}/{h}_d.exr", depth)
        for job, extra in jobs.items():
            peaks = [_peak_rss_bytes([sys.executable, "-m", "dcdi_core", job, "--image", f"{d}/{h}.exr", "--depth",
                                      f"{d}/{h}_d.exr", "--lens", "mos-s1", *extra, "-o", f"{d}/out.exr"])
                     for h, w in sizes]
            per_px = (peaks[1] - peaks[0]) / (sizes[1][0] * sizes[1][1] - sizes[0][0] * sizes[0][1])
            print(f"| {job} | {gib(peaks[0])} | {gib(peaks[1])} | {per_px:.0f} | {JOB_BYTES_PER_PIXEL[job]} |")
    return 0


DEPTH_GOAL_S = 10.0       # `dcdi depth estimate` at 1280 x 1920, whole process


def bench_depth(quick: bool = False, repeat: int = 2) -> int:
    """`dcdi depth estimate` (the depth from a capture's own blur, MOS-S1):
    whole processes on a synthetic capture (the bench's RGB-D simulated
    through MOS-S1 at 12.2 um with sensor noise) of 1280 x 1920 (320 x 480
    with --quick), once to warm the caches then the best of ``repeat``,
    beside its goal and the start-up; then one run in process, its stages."""
    import sys
    from ..outputs import scratch_folder

    from ..dfd import estimate_depth
    from ..io.images import write_image
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    from ..render.noise import add_sensor_noise
    from ..render.simulate import SimulateOptions, simulate
    from ..render.synthetic import synthetic_rgbd
    from ..app import PSFRequest, open_source
    h, w = (320, 480) if quick else (1280, 1920)
    lens = load_lens("mos-s1")
    g = ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122)
    library = open_source(lens, g, PSFRequest()).library
    img, depth = synthetic_rgbd(h, w, seed=0)
    capture = add_sensor_noise(simulate(img, depth, lens, SimulateOptions(geometry=g), library=library).image, seed=1)
    print(f"bench depth: dcdi depth estimate, MOS-S1, a {h} x {w} synthetic capture at 12.2 um with noise, "
          f"{os.cpu_count()} CPU(s), load average {os.getloadavg()[0]:.1f}; wall (CPU) seconds, best of {repeat} "
          "after a warm-up run")
    with scratch_folder() as d:
        write_image(f"{d}/cap.exr", capture)
        py = [sys.executable, "-m", "dcdi_core"]
        base, _ = min(_process(py + ["--help"]) for _ in range(2))
        cmd = py + ["depth", "estimate", "--image", f"{d}/cap.exr", "--camera", "mos-s1", "--image-pixel-pitch",
                    "0.0122", "-o", f"{d}/d.exr"]
        _run_rows({"dcdi --help (start-up)": (py + ["--help"], None),
                   "dcdi depth estimate": (cmd, None if quick else DEPTH_GOAL_S)}, repeat, quick, base)
    t, c = time.perf_counter(), time.process_time()
    est = estimate_depth(capture, library, g)
    stages = ", ".join(f"{k} {v:.2f}" for k, v in est.info["seconds"].items())
    print(f"  in process: {time.perf_counter() - t:.2f} s ({time.process_time() - c:.2f} s CPU): {stages}")
    return 0


def run(what: str, args) -> int:
    if what == "memory":
        return bench_memory(getattr(args, "quick", False))
    if what == "cli":
        quick = getattr(args, "quick", False)
        return bench_cli(quick, repeat=1 if quick else 2)
    if what == "dacn":
        return bench_dacn(getattr(args, "quick", False), getattr(args, "threads", 1))
    if what == "correction":
        return bench_correction(getattr(args, "quick", False))
    if what == "render":
        return bench_render(getattr(args, "quick", False))
    if what == "trace":
        optiland = getattr(args, "optiland", None)
        if optiland is not None:
            check_optiland(optiland)
        return bench_trace(args.rays, args.repeat, optiland)
    if what == "psflib":
        return bench_psflib(getattr(args, "quick", False))
    if what == "depth":
        quick = getattr(args, "quick", False)
        return bench_depth(quick, repeat=1 if quick else 2)
    raise ValueError(f"unknown benchmark {what!r}")
