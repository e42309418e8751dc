"""`dcdi bench`: timings printed, never asserted.

Each benchmark times the real code path and a simple baseline in the same
process and prints the ratio, so that figures from different machines compare.
One module per group: ``trace`` (the tracer, beside Optiland 0.6.3 with
``optiland_spot.py``, and the PSF library), ``render`` (simulation and
bokeh), ``sampling`` (PSFs sampled for the image: error and time),
``quality`` (each knob of the PSF work against the converged render, and the
error budget's plans),
``correction`` (the deconvolution and the DACN), ``processes`` (whole
commands: times, peak memory, the depth estimate); ``timing`` holds
their helpers. Each is imported when its benchmark runs.
"""
from __future__ import annotations


def run(what: str, *, quick: bool = False, threads: int = 1, lens=None, sizes=None, measure: bool = False,
        rays: int = 1 << 20, repeat: int = 3, optiland=None) -> int:
    """Run the benchmark ``what`` (the `dcdi bench` choices) with its
    settings, given as values (the command line's options are read in
    ``cli.bench``): ``quick`` smaller workloads; ``threads`` torch's (dacn);
    ``lens``, ``sizes`` (rows, cols) and ``measure`` (quality); ``rays``,
    ``repeat`` and ``optiland`` (trace)."""
    if what == "memory":
        from .processes import bench_memory
        return bench_memory(quick)
    if what == "cli":
        from .processes import bench_cli
        return bench_cli(quick, repeat=1 if quick else 2)
    if what == "dacn":
        from .correction import bench_dacn
        return bench_dacn(quick, threads)
    if what == "correction":
        from .correction import bench_correction
        return bench_correction(quick)
    if what == "quality":
        from .quality import bench_quality
        return bench_quality(lens, quick, tuple(map(tuple, sizes)) if sizes else None, measure)
    if what == "sampling":
        from .sampling import bench_sampling
        return bench_sampling(quick)
    if what == "render":
        from .render import bench_render
        return bench_render(quick)
    if what == "trace":
        from .trace import bench_trace, check_optiland
        if optiland is not None:
            check_optiland(optiland)
        return bench_trace(rays, repeat, optiland)
    if what == "psflib":
        from .trace import bench_psflib
        return bench_psflib(quick)
    if what == "depth":
        from .processes import bench_depth
        return bench_depth(quick, repeat=1 if quick else 2)
    raise ValueError(f"unknown benchmark {what!r}")
