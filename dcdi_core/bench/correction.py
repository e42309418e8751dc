"""`dcdi bench correction` and `dcdi bench dacn`: the deconvolution against the
simulation that makes its capture, and the DACN's inference per configuration."""
from __future__ import annotations

import math
import os
import time

import numpy as np

from .timing import _best


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
    from ..psf.sources import PSFRequest, open_source
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


