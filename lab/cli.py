"""The lab's one entry point, run from the repository's root:

    python -m lab report NAME ...       an accuracy report (error against time), NAME one of
                                        psf-accuracy, simulation-accuracy, olf, psf-source,
                                        correction, pipeline, depth
    python -m lab COMMAND ...           a study, a benchmark against a reference, a tool:
                                        dacn-study, dfd-refine-study, olf-sweep, depth-from-blur,
                                        bench-defocus, bokeh-variants, capture-records,
                                        resample-accuracy, focus-stack, raymap, aperture, catalogue-table,
                                        contact-sheet, large-bokeh, quality-tables, cli-reference,
                                        reproduce, traced-render, breathing, walk, olf-frame,
                                        olf-basis, olf-rays

`python -m lab COMMAND --help` says more; lab/README.md lists which figure or
table of docs/ each one makes. The lab uses the engine (``dcdi_core``); the
engine never uses the lab. A report's paths are checked before any work, as
the `dcdi` command checks its verbs' (``dcdi_core.cli.files``); an error a
user can cause ends in one line, ``lab: error: ...``, exit status 2.
Engine imports are inside the handlers: a report loads torch only when it
scores the networks.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from dcdi_core.cli.common import add_subcommands, lens_map, positive_int
from dcdi_core.cli.files import Spec, label_of

#: the commands that are a lab module's own ``main(argv)``
MODULES = {
    "dacn-study": ("dacn_study", "the DACN study: each ingredient of the correction at equal budget "
                                 "(docs/correction.md)"),
    "dfd-refine-study": ("dfd_refine_study", "does the learned refinement of the depth from blur earn its place "
                                             "(docs/depth.md)"),
    "olf-sweep": ("olf_sweep", "the Omni-Lens-Field's size x learning-rate sweep (docs/olf.md)"),
    "depth-from-blur": ("depth_from_blur_report", "the depth from a capture's blur against the truth (docs/depth.md)"),
    "dof-rule": ("dof_rule_report", "when dcdi dof trusts the depth from the capture's blur: the chain's gain "
                                    "against the frame's confidence (docs/depth.md)"),
    "bench-defocus": ("bench_defocus", "the lens bokeh beside Blender's Defocus node: the engine's side and the "
                                       "scores (python build.py bench render; docs/performance.md)"),
    "bokeh-variants": ("bokeh_variants", "the bokeh's variants, error against time (docs/performance.md)"),
    "capture-records": ("capture_record_report", "what a capture's record changes downstream "
                                                 "(docs/capture-records.md)"),
    "resample-accuracy": ("resample_accuracy", "the warp's resampling methods, error against time "
                                               "(docs/image-formation.md)"),
    "focus-stack": ("focus_stack_report", "a focus stack's PSFs against tracing, and their time (docs/psf.md)"),
    "catalogue-table": ("catalogue_table", "the lens catalogue's figures beside its sources' (lenses/README.md)"),
    "large-bokeh": ("large_bokeh", "an 85 mm f/1.4 at 1920 x 1080 with a 190-px background blur, timed whole "
                                   "(docs/performance.md)"),
    "contact-sheet": ("contact_sheet", "one scene through every lens wide open, and one lens stopped down "
                                       "(lenses/README.md)"),
    "raymap": ("raymap_report", "the catalogue's ray maps against tracing at held-out field, depth, focus and "
                                "f-number, beside a PSF basis (docs/psf.md)"),
    "aperture": ("aperture_report", "the iris on the PSFs: defocus blur against the f-number, the blades' "
                                    "polygons (docs/psf.md)"),
    "quality-tables": ("quality_tables", "the error tables the planner plans by: each knob of the PSF work "
                                         "against the converged render, per lens and pitch (docs/performance.md)"),
    "cli-reference": ("cli_reference", "the `dcdi` command's reference page, docs/cli.md, from its parser"),
    "reproduce": ("reproduce", "a shipped network from scratch, from its config in lab/configs/"),
    "breathing": ("breathing", "each lens's focus breathing and depth-dependent distortion: the chief-ray map "
                               "against a direct trace (docs/image-formation.md)"),
    "olf-frame": ("olf_frame", "an OLF whose head draws each PSF in coordinates scaled to its blur, against the "
                               "pixel head (docs/olf.md)"),
    "olf-basis": ("olf_basis", "an OLF giving the coefficients of a basis of blur-scaled PSFs, against the basis "
                               "and the grid interpolated (docs/olf.md)"),
    "olf-rays": ("olf_rays", "an OLF in ray space: an MLP giving where the rays land, deposited as the ray map's, "
                             "against the ray map (docs/olf.md)"),
    "walk": ("walk", "a job's calls through the layers: `dcdi dof` and Apply Lens Bokeh cross into app once "
                     "(docs/design.md)"),
    "traced-render": ("traced_render", "the fast bokeh (--distort --focus) against a render traced through the lens, "
                                       "every catalogue lens (docs/image-formation.md)"),
}

#: the reports' options that never name a path, beside the `dcdi` command's (``dcdi_core.cli.files.NOT_PATHS``)
NOT_PATHS = frozenset({"count", "held_out_points", "pitch_only", "points", "compare", "basis_lens", "seed", "ceiling_rays",
                        "frame_px", "reference_rays"})

#: what each report reads and writes (``dcdi_core.cli.files.Spec``), checked before any work
SPECS = {
    "psf-accuracy": Spec(reads=("lens",), into=("out",)),
    "simulation-accuracy": Spec(reads=("lens",), into=("out",)),
    "olf": Spec(reads=("olf", "sweep"), into=("out",)),
    "psf-source": Spec(reads=("lens",), into=("out",)),
    "correction": Spec(reads=("lens", "data"), into=("out",), updates=("data",)),
    "pipeline": Spec(reads=("pairs", "dacn", "depth_model", "baseline", "olf", "target"), into=("out",),
                     updates=("pairs",)),
    "depth": Spec(reads=("pairs", "dacn", "depth_model", "baseline", "train_pairs"), into=("out",),
                  updates=("pairs", "train_pairs")),
}


def _report_models(args, lenses, need_dacn: bool = True):
    """{lens: {'dacn', 'depth', 'baseline'}} for the pipeline and depth reports:
    given paths, else the shipped files (dcdi_core.shipped)."""
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.models.depth.export import load_depthnet
    from dcdi_core.errors import ModelError
    from dcdi_core.shipped import network
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

    from . import pipeline_report as pr
    from dcdi_core.optics.lens import load_lens
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

    from dcdi_core.atomic import write_text
    from . import pipeline_report as pr
    torch.set_num_threads(args.threads)
    pairs = lens_map(args.pairs, "--pairs")
    models = _report_models(args, pairs, need_dacn=False)
    missing = [lens for lens in pairs if models[lens]["depth"] is None]
    if missing:
        from dcdi_core.errors import ModelError
        raise ModelError(f"no depth network for {', '.join(missing)}: give --depth-model LENS=MODEL")
    constants = {lens: pr.median_depth_m(d) for lens, d in lens_map(args.train_pairs, "--train-pairs").items()}
    res = pr.depth_report(pairs, {k: v["depth"] for k, v in models.items()}, {}, args.count, constants)
    text = pr.depth_markdown(res)
    write_text(Path(args.out) / "depth.md", text)
    write_text(Path(args.out) / "depth.json", json.dumps(res, indent=1) + "\n")
    print(text, end="")
    return 0


def cmd_report_psf(args) -> int:
    from .psf_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_sim(args) -> int:
    from .simulation_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_olf(args) -> int:
    from .olf_report import run_report
    return run_report(args.olf, args.out, quick=args.quick, sweep=args.sweep, pitch_only=args.pitch_only,
                      held_out_points=args.held_out_points, ceiling_rays=args.ceiling_rays,
                      frame_px=args.frame_px or (), reference_rays=args.reference_rays or ())


def cmd_report_psf_source(args) -> int:
    from .psf_source_report import run_report
    return run_report(args.lens, args.out, points=args.points, quick=args.quick)


def cmd_report_correction(args) -> int:
    from .correction_report import ReportOptions, run_report
    options = ReportOptions(lenses=tuple(args.lens or ("mos-s1", "mos-s2")), data=tuple(args.data or ()),
                            quick=args.quick, frames=args.frames, threads=args.threads)
    run_report(options, args.out, log=lambda t: print(t, file=sys.stderr, flush=True))
    print((Path(args.out) / "report.md").read_text(encoding="utf-8"), end="")
    return 0


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


def add_reports(rsub) -> None:
    """The reports, each a subcommand of ``rsub`` (`python -m lab report NAME`)."""
    r = rsub.add_parser("psf-accuracy", help="PSF error vs build time for rays, wavelengths, bins, precision")
    r.add_argument("lens", help="lens id or .toml path")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown) and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="a smaller reference and sweep (for tests)")
    r.set_defaults(func=cmd_report_psf)
    r = rsub.add_parser("simulation-accuracy",
                        help="patch-wise simulation vs a per-pixel reference; bokeh at depth edges")
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
                        "(compares an old and a new OLF on the same traced points), and a lens's ray map "
                        "there, the ceiling of an OLF learned from it")
    r.add_argument("--ceiling-rays", type=positive_int, action="append", default=None, metavar="N",
                   help="with --held-out-points: the ray map's rows with N rays a side (repeat; default: the "
                        "OLF's own)")
    r.add_argument("--frame-px", type=positive_int, action="append", default=None, metavar="M",
                   help="with --held-out-points: the held-out PSFs through an M x M frame scaled to each one's "
                        "thin-lens blur and back (repeat): the ceiling of a head that draws a disc of any radius "
                        "in M x M outputs")
    r.add_argument("--reference-rays", type=positive_int, action="append", default=None, metavar="N",
                   help="with --held-out-points: the held-out points traced again with N rays a side (repeat; "
                        "about 15 s a point at 1024): the stored traces' own error, and the ray map's rows "
                        "against these traces")
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m lab", description=__doc__.split("\n\n")[0].rstrip(":") + ".",
                                epilog="lab/README.md: each study, and the command that makes each figure of docs/.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    q = sub.add_parser("report", help="accuracy reports (error against run time)")
    rsub = add_subcommands(q, "report_command", "REPORT")
    add_reports(rsub)
    for name, r in rsub.choices.items():
        spec = SPECS[name]
        r.set_defaults(files=spec, files_labels={d: label_of(r, d) for d in (*spec.reads, *spec.writes, *spec.into)})
    for name, (_, helptext) in MODULES.items():
        sub.add_parser(name, help=helptext, add_help=False)
    return p


def _report(args) -> int:
    """One report: its paths checked first, its outputs together, an error a user can cause in one line."""
    from dcdi_core.cli.common import error_words, one_line
    from dcdi_core.cli.files import job_files
    from dcdi_core.errors import DcdiError
    try:
        files = job_files(args)
        files.check()
        with files.together():
            return args.func(args)
    except DcdiError as e:
        print(f"lab: error: {one_line(e.in_words(error_words(args)))}", file=sys.stderr)
        return 2


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in MODULES:
        module = importlib.import_module(f"lab.{MODULES[argv[0]][0]}")
        return module.main(argv[1:]) or 0
    return _report(build_parser().parse_args(argv))
