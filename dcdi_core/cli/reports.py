"""`dcdi report ...`, `dcdi bench` and `dcdi demo`: accuracy reports,
benchmarks and the demo job (dcdi_core.experiments and dcdi_core.demo).

Engine imports are inside the handlers: a report loads torch only when it
scores the networks.
"""
from __future__ import annotations

import sys
from pathlib import Path

from .common import add_subcommands, lens_map, positive_int


def _report_models(args, lenses, need_dacn: bool = True):
    """{lens: {'dacn', 'depth', 'baseline'}} for the pipeline and depth reports:
    given paths, else the shipped files (models.registry)."""
    from ..models.dacn.correct import load_dacn
    from ..models.depth.export import load_depthnet
    from ..models.errors import ModelError
    from ..models.registry import network
    dacn, depth, base = (lens_map(v, w) for v, w in ((args.dacn, "--dacn"), (args.depth_model, "--depth-model"),
                                                      (args.baseline, "--baseline")))
    models = {}
    for lens in lenses:
        d = dacn.get(lens) or network("dacn").shipped_file(lens)
        if d is None and need_dacn:
            raise ModelError(f"no DACN for {lens}: give --dacn {lens}=MODEL")
        z = depth.get(lens) or network("depth").shipped_file(lens)
        models[lens] = {"dacn": load_dacn(d)[0] if d else None, "depth": load_depthnet(z)[0] if z else None,
                        "baseline": load_dacn(base[lens])[0] if lens in base else None}
    return models


def cmd_report_pipeline(args) -> int:
    import torch

    from ..experiments import pipeline_report as pr
    from ..optics.lens import load_lens
    torch.set_num_threads(args.threads)
    pairs = lens_map(args.pairs, "--pairs")
    models = _report_models(args, pairs)
    target = load_lens(args.target)
    keep = tuple(args.keep)
    results, times = {}, {}
    for lens, d in pairs.items():
        ids = pr.held_out(d, [], args.count)
        print(f"{lens}: {len(ids)} held-out pairs of {d}", file=sys.stderr)
        results[lens] = pr.lens_rows(lens, d, ids, models[lens], target, keep, olf_file=args.olf,
                                     pictures=Path(args.out) / "pictures",
                                     log=lambda t: print(t, file=sys.stderr))
        for size in ([] if args.quick else [(480, 640), (1280, 1920)]):
            times[f"{lens}, {size[0]} x {size[1]}"] = pr.stage_times(models[lens], target, keep, size,
                                                                   olf_file=args.olf)
    print(pr.write_report(args.out, results, times, target.id, keep), end="")
    return 0


def cmd_report_depth(args) -> int:
    import json

    import torch

    from ..atomic import write_text
    from ..experiments import pipeline_report as pr
    torch.set_num_threads(args.threads)
    pairs = lens_map(args.pairs, "--pairs")
    models = _report_models(args, pairs, need_dacn=False)
    missing = [lens for lens in pairs if models[lens]["depth"] is None]
    if missing:
        from ..models.errors import ModelError
        raise ModelError(f"no depth network for {', '.join(missing)}: give --depth-model LENS=MODEL")
    constants = {lens: pr.median_depth_m(d) for lens, d in lens_map(args.train_pairs, "--train-pairs").items()}
    res = pr.depth_report(pairs, {k: v["depth"] for k, v in models.items()}, {}, args.count, constants)
    text = pr.depth_markdown(res)
    write_text(Path(args.out) / "depth.md", text)
    write_text(Path(args.out) / "depth.json", json.dumps(res, indent=1) + "\n")
    print(text, end="")
    return 0


def cmd_report_psf(args) -> int:
    from ..experiments.psf_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_sim(args) -> int:
    from ..experiments.simulation_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_olf(args) -> int:
    from ..experiments.olf_report import run_report
    return run_report(args.olf, args.out, quick=args.quick, sweep=args.sweep, pitch_only=args.pitch_only,
                      held_out_points=args.held_out_points)


def cmd_report_psf_source(args) -> int:
    from ..experiments.psf_source_report import run_report
    return run_report(args.lens, args.out, points=args.points, quick=args.quick)


def cmd_report_correction(args) -> int:
    from ..experiments.correction_report import ReportOptions, run_report
    options = ReportOptions(lenses=tuple(args.lens or ("mos-s1", "mos-s2")), data=tuple(args.data or ()),
                            quick=args.quick, frames=args.frames, threads=args.threads)
    run_report(options, args.out, log=lambda t: print(t, file=sys.stderr, flush=True))
    print((Path(args.out) / "report.md").read_text(encoding="utf-8"), end="")
    return 0


def cmd_report_dataset(args) -> int:
    from ..experiments.dataset_report import DatasetReportOptions, run_report
    options = DatasetReportOptions(lenses=tuple(args.lens or ("mos-s1", "mos-s2")), frames=args.frames,
                                   seed=args.seed)
    run_report(args.dirs, options, args.out, log=lambda t: print(t, file=sys.stderr, flush=True))
    print((Path(args.out) / "report.md").read_text(encoding="utf-8"), end="")
    return 0


def cmd_bench(args) -> int:
    from ..experiments import bench
    return bench.run(args.what, args)


def cmd_demo(args) -> int:
    from .. import demo
    return demo.run(args.out)


def _network_report(rsub, name: str, helptext: str):
    """`report pipeline` or `report depth`: networks scored on held-out factory pairs."""
    r = rsub.add_parser(name, help=helptext)
    r.add_argument("--pairs", action="append", required=True, metavar="LENS=DIR",
                   help="a camera lens's DA2T pairs (their test split is used), e.g. mos-s1=out/pairs-mos-s1")
    r.add_argument("--dacn", action="append", default=None, metavar="LENS=MODEL",
                   help="a lens's DACN (default: the shipped one)")
    r.add_argument("--depth-model", action="append", default=None, metavar="LENS=MODEL",
                   help="a lens's depth network (default: the shipped one)")
    r.add_argument("--baseline", action="append", default=None, metavar="LENS=MODEL",
                   help="a lens's depth-unaware DACN (a row of its own)")
    r.add_argument("--count", type=positive_int, default=8, help="held-out pairs per lens (default 8)")
    r.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown), JSON and pictures")
    return r


def add_commands(sub) -> None:
    q = sub.add_parser("report", help="accuracy reports (error against run time)")
    rsub = add_subcommands(q, "report_command", "REPORT")
    r = rsub.add_parser("psf-accuracy", help="PSF error vs build time for rays, wavelengths, bins, precision")
    r.add_argument("lens", help="lens id or .toml path")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown) and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="a smaller reference and sweep (for tests)")
    r.set_defaults(func=cmd_report_psf)
    r = rsub.add_parser("simulation-accuracy", help="patch-wise simulation vs a per-pixel reference; bokeh at depth edges")
    r.add_argument("--lens", default="mos-s1", help="lens id (default mos-s1)")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown)")
    r.add_argument("--quick", action="store_true", help="a small image and sweep (for tests)")
    r.set_defaults(func=cmd_report_sim)
    r = rsub.add_parser("olf", help="Omni-Lens-Field: PSF error vs storage and time, PSF-map time, downstream images")
    r.add_argument("--olf", action="append", default=None, metavar="FILE.npz",
                   help="an OLF file (repeat for several; default: the shipped ones)")
    r.add_argument("--sweep", default=None, metavar="RESULTS.jsonl",
                   help="rows of the size x learning-rate sweep (out/sweep/results.jsonl) for the table and plot")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown), JSON and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="few points and small images (for tests)")
    r.add_argument("--pitch-only", action="store_true",
                   help="only the kernels at coarser pixel pitches (area-resampled) against kernels traced there")
    r.add_argument("--held-out-points", default=None, metavar="RUN/points.npz",
                   help="only: every file scored on one training run's held-out points, per lens and focus "
                        "(compares an old and a new OLF on the same traced points)")
    r.set_defaults(func=cmd_report_olf)
    r = rsub.add_parser("psf-source", help="every PSF source (basis ranks, libraries, the OLF): off-grid and grid "
                                           "error vs storage, PSF-map time, downstream images",
                        description="Scores each source against kernels traced with 1024 rays per pupil side at "
                                    "points off every grid (cached in the output folder), a random 1 % of its "
                                    "own grid, its storage, build time, the time of a 1280 x 1920 PSF map, and "
                                    "a simulation and a bokeh with it against traced PSFs. Tens of minutes on "
                                    "2 cores the first time (the references), minutes after.")
    r.add_argument("--lens", action="append", default=None, choices=["mos-s1", "mos-s2", "6p", "double-gauss"],
                   help="a lens (repeat; default: the four with a shipped basis)")
    r.add_argument("--points", type=positive_int, default=32, help="off-grid reference points per lens (default 32)")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown), JSON and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="6 points and small images (for tests)")
    r.set_defaults(func=cmd_report_psf_source)

    r = rsub.add_parser("correction", help="deconvolution with the lens's own PSFs against the truth, beside the "
                                           "capture, one-depth deconvolution and the shipped DACN; settings "
                                           "against time")
    r.add_argument("--lens", action="append", default=None, metavar="LENS",
                   help="a lens id (repeat for several; default mos-s1 and mos-s2)")
    r.add_argument("--data", action="append", default=None, metavar="FACTORY_DIR",
                   help="a factory folder (or another RGB-D source) whose frames join the synthetic scenes "
                        "(repeat for several)")
    r.add_argument("--frames", type=positive_int, default=2, help="frames per --data folder (default 2)")
    r.add_argument("--threads", type=positive_int, default=1, help="torch threads for the DACN (default 1)")
    r.add_argument("--out", default="out/report", help="folder for report.md, results.json and the pictures")
    r.add_argument("--quick", action="store_true", help="small frames, one seed, no traced PSFs (for tests)")
    r.set_defaults(func=cmd_report_correction)

    r = rsub.add_parser("dataset", help="what factory frames hold, per recipe: texture (high-frequency share), "
                                        "depth mix, clipping, and the share of 128 px crops whose capture through "
                                        "a lens is already above 40 dB")
    r.add_argument("dirs", nargs="+", metavar="DIR", help="one or more factory folders (frames grouped by recipe "
                                                          "across them)")
    r.add_argument("--lens", action="append", default=None, metavar="LENS",
                   help="a lens id for the blur measure (repeat for several; default mos-s1 and mos-s2)")
    r.add_argument("--frames", type=positive_int, default=None,
                   help="at most this many frames per recipe, chosen evenly (default all)")
    r.add_argument("--seed", type=int, default=0, help="the frames' random places on the sensor (default 0)")
    r.add_argument("--out", default="out/dataset-report", help="folder for report.md, results.json and a picture "
                                                               "per recipe (default out/dataset-report)")
    r.set_defaults(func=cmd_report_dataset)

    r = _network_report(rsub, "pipeline", "DCDI end to end on held-out factory pairs against the ideal; stage times")
    r.add_argument("--target", default="6p", help="the target lens (default 6p)")
    r.add_argument("--keep", type=float, nargs=2, default=[0.7, 1.5], metavar=("NEAR", "FAR"),
                   help="depth range kept sharp, metres (default 0.7 1.5)")
    r.add_argument("--olf", default=None, metavar="FILE.npz", help="the OLF (default: the shipped one)")
    r.add_argument("--quick", action="store_true", help="no stage timing at full sizes (for tests)")
    r.set_defaults(func=cmd_report_pipeline)
    r = _network_report(rsub, "depth", "the depth network on held-out factory pairs: AbsRel, RMSE, delta1")
    r.add_argument("--train-pairs", action="append", default=None, metavar="LENS=DIR",
                   help="the pairs a lens's network learned from: their median depth is the constant row")
    r.set_defaults(func=cmd_report_depth)

    q = sub.add_parser("bench", help="benchmarks (times, not tests)",
                       description="Benchmarks of the engine; the dataset factory's is `python build.py bench "
                                   "factory` (it starts the Blender layer, which the engine never does).")
    q.add_argument("what", choices=["trace", "psflib", "render", "dacn", "correction", "cli", "memory", "depth"],
                   help="what to benchmark (cli: the simulate and bokeh commands' whole processes; memory: "
                        "their peak memory per pixel, against the estimate that refuses images too large; depth: "
                        "dcdi depth estimate's whole process beside its goal)")
    q.add_argument("--rays", type=positive_int, default=1 << 20, help="rays per trace (default 2^20)")
    q.add_argument("--repeat", type=positive_int, default=3, help="timed repetitions (best is kept)")
    q.add_argument("--quick", action="store_true", help="psflib, render, dacn, correction, depth: smaller (for tests)")
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
