"""`dcdi bench render`: the simulation and the bokeh at 1280 x 1920, their paths
(exact, fast, numpy-only, torch, low-rank, multi-resolution) beside a direct
per-patch convolution."""
from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from .timing import _best


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
    from ..render.simulate import SimulateOptions, simulate
    from ..psf.sources import open_library
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
        from .processes import goal_rows
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
    and library): ``python -c "from dcdi_core.bench.render import
    bench_simulation_paths as b; b()"``."""
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    from ..psf.sources import open_library
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

    from ..models.common.metrics import psnr
    from ..render.geometry import ImageGeometry
    from ..render.multires import BENCH_C, DEFAULT_MAX_LEVEL
    from ..render.bokeh import BokehOptions, bokeh
    from ..psf.sources import open_library

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
                  f"exact {t_ex:.2f} s (x{t_ex / t_mr:.2f}); "
                  f"PSNR vs exact {psnr(res / peak, exact / peak, 1.0):.2f} dB, "
                  f"max |diff| {np.abs(res - exact).max() / peak:.4f} of the peak; peak memory "
                  f"{peak_mr / 2**20:.0f} against {peak_ex / 2**20:.0f} MiB; load average {os.getloadavg()[0]:.1f}",
                  flush=True)


