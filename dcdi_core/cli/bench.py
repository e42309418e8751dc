"""`dcdi bench` and `dcdi demo`: the engine's benchmarks (``dcdi_core.bench``)
and the demo job (``dcdi_core.demo``). Engine imports are inside the handlers."""
from __future__ import annotations

from .common import positive_int


def cmd_bench(args) -> int:
    from .. import bench
    return bench.run(args.what, quick=args.quick, threads=args.threads, lens=args.lens, sizes=args.size,
                     measure=args.measure, rays=args.rays, repeat=args.repeat, optiland=args.optiland)


def cmd_demo(args) -> int:
    from .. import demo
    return demo.run(args.out)


def add_commands(sub) -> None:
    q = sub.add_parser("bench", help="benchmarks (times, not tests)",
                       description="Benchmarks of the engine; the dataset factory's is `python build.py bench "
                                   "factory` (it starts the Blender layer, which the engine never does).")
    q.add_argument("what", choices=["trace", "psflib", "render", "sampling", "quality", "dacn", "correction", "cli", "memory",
                                    "depth"],
                   help="what to benchmark (sampling: a focus change's PSFs sampled for the image, error against time; "
                        "quality LENS: each knob of the PSF work (rays, wavelengths, field step) against the converged "
                        "render, and the planner's choice for each error budget, rendered; cli: the simulate and bokeh commands' whole processes; memory: "
                        "their peak memory per pixel, against the estimate that refuses images too large; depth: "
                        "dcdi depth estimate's whole process beside its goal)")
    q.add_argument("lens", nargs="?", default=None, help="quality: the lens (id or .toml path)")
    q.add_argument("--size", type=positive_int, nargs=2, action="append", default=None, metavar=("H", "W"),
                   help="quality: an image size (repeat the option; default: the sizes of the lens's table)")
    q.add_argument("--measure", action="store_true",
                   help="quality: measure the knob table again instead of printing the lens's shipped one")
    q.add_argument("--rays", type=positive_int, default=1 << 20, help="rays per trace (default 2^20)")
    q.add_argument("--repeat", type=positive_int, default=3, help="timed repetitions (best is kept)")
    q.add_argument("--quick", action="store_true", help="psflib, render, sampling, dacn, correction, depth: smaller (for tests)")
    q.add_argument("--threads", type=positive_int, default=1, help="dacn: torch threads (default 1)")
    q.add_argument("--optiland", default=None, metavar="PYTHON",
                   help="trace: also the MOS-S1 spot work beside Optiland 0.6.3, run by this interpreter (one with "
                        "optiland==0.6.3: python build.py bench trace makes .venv-optiland/)")
    q.set_defaults(func=cmd_bench)

    q = sub.add_parser("demo", help="the demo job: DCDI end to end on a synthetic scene (a MOS-S1 capture, its correction "
                                    "and depth, the 6P's depth of field beside the ideal), lens reports, spot "
                                    "diagrams, PSFs, simulation and bokeh (python build.py demo adds a factory scene)")
    q.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    q.set_defaults(func=cmd_demo)
