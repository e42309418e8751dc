"""`dcdi depth train|export`: the small metric-depth network on a lens's
captures (the pipeline's default depth estimator).

Engine imports are inside the handlers: torch is loaded only once a command
needs it.
"""
from __future__ import annotations

from .common import add_export_options, add_subcommands, exported, positive_int, run_training


def cmd_depth_train(args) -> int:
    from pathlib import Path

    from ..models.depth.config import DepthTrainConfig
    config = DepthTrainConfig(data=args.data, widths=tuple(args.widths), input=args.input, iters=args.iters,
                              batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed, threads=args.threads,
                              checkpoint_every=args.checkpoint_every)
    from ..models.depth.train import train_depth       # torch from here on
    run = Path(args.output)
    result = run_training("depth train", run, lambda **kw: train_depth(config, run, **kw), config.checkpoint_every)
    if result is None:
        return 130
    v = result.validation
    print(f"trained {run} ({result.step} iterations, {result.seconds:.1f} s here)"
          + (f"; validation (EMA, from the {args.input}): AbsRel {v['abs_rel']:.3f}, RMSE {v['rmse']:.2f} m, "
             f"delta1 {v['delta1']:.3f}" if v else ""))
    return 0


def cmd_depth_export(args) -> int:
    from ..models.depth.export import export_depthnet
    return exported(args, export_depthnet(args.run, args.output, weights=args.weights, dtype=args.dtype))


def cmd_depth_estimate(args) -> int:
    """`dcdi depth estimate`: metric depth of a capture from its own lens's blur."""
    from ..app import depth as job
    from ..dfd import DepthFromBlurOptions
    from ..io.image_checks import check_depth_output
    from ..io.images import read_image, write_depth
    from ..optics.lens import load_lens
    from .common import check_cache, dump, in_cli_words, job_control, psf_request, say
    from .correct import _correct_render, _recorded
    from .render import check_image_fits
    out = check_depth_output(args.output)                   # -o and --confidence apart: outputs.JobFiles
    conf_out = check_depth_output(args.confidence) if args.confidence else None
    lens = load_lens(args.camera)
    options = DepthFromBlurOptions(tile=args.tile, window=2 * args.tile)
    check_cache()
    check_image_fits(args, "correct")
    image = read_image(args.image)
    refine = None if args.refine == "none" else args.refine
    request = job.DepthRequest(image, lens, render=_correct_render(args, lens), psf=psf_request(args),
                               options=options, recorded=_recorded(args.image), image_name=f"the image {args.image}",
                               refine=refine)
    r = job.estimate(request, job_control("dcdi depth estimate", args))
    notes = in_cli_words(args, r.notes)
    for note in notes:
        say(f"note: {note}")
    write_depth(out, r.depth_m)
    if conf_out is not None:
        write_depth(conf_out, r.confidence)
    print(dump({"output": str(out), "confidence": str(conf_out) if conf_out else None,
                "size": [image.shape[0], image.shape[1]], "lens": lens.id,
                "pixel_pitch_mm": r.geometry.pixel_pitch_mm, "psf_source": r.info["psf_source"],
                "noise": r.info["noise_from"], "refined": r.info["refined"], "confident_share": round(r.info["confident_share"], 3),
                "depth_range_m": [round(float(r.depth_m.min()), 3), round(float(r.depth_m.max()), 3)],
                "seconds": {k: round(v, 3) for k, v in r.seconds.items()}, "notes": notes}))
    return 0


def estimate_parser(subparsers):
    from .common import add_psf_options, add_psf_source_options
    t = subparsers.add_parser(
        "estimate", help="metric depth of a capture from its own lens's blur (numpy; no network)",
        description="Metric depth of a capture from the blur of the lens that took it: for each tile, the depth "
                    "whose PSFs (at the tile's field) best explain the tile's spectrum under a natural-image "
                    "prior, a confidence (the posterior's mass within 15 %% of the estimate), and tiles without "
                    "texture filled from confident ones along the capture's edges. Uses the capture's recorded "
                    "pixel pitch, axis and focus where the file has them. Depths in metres, within the PSF "
                    "library's range (0.7-10 m). Prints what it did as JSON.")
    t.add_argument("--image", required=True, help="the capture (EXR linear, or PNG/JPEG sRGB)")
    t.add_argument("--camera", required=True, help="the lens that took it (a shipped id or a lens file)")
    t.add_argument("-o", "--output", required=True, help="the depth map (EXR 'Z' or .npy), metres")
    t.add_argument("--confidence", default=None, metavar="FILE", help="also write the confidence map (0-1) there (EXR 'Z' or .npy)")
    t.add_argument("--axis", type=float, nargs=2, default=None, metavar=("ROW", "COL"),
                   help="the optical axis's pixel position in the image (default: the record's, else its centre)")
    t.add_argument("--refine", default="auto", metavar="FILE|none",
                   help="the learned refinement of the tiles' depths: auto (default: --camera's shipped one, where "
                        "the capture has the pixel pitch it learned), none (the blur's evidence alone), or a file")
    t.add_argument("--tile", type=positive_int, default=32,
                   help="px between estimates (default 32; each read from a window twice as wide)")
    add_psf_options(t, sensor_focus=True, render=True)
    add_psf_source_options(t)
    t.set_defaults(func=cmd_depth_estimate, words={"lens": "--camera", "camera": "--camera"})
    return t


def train_parser(subparsers, name: str, **kw):
    """The parser of `depth train`."""
    t = subparsers.add_parser(name, **kw,
                              description="Train the depth network (capture -> metric depth) on pre-built DA2T "
                                          "pairs: seeded, atomic checkpoints, exact resume, the split by scene of "
                                          "the pairs.")
    t.add_argument("--data", required=True, help="pairs folder (dcdi dacn pairs)")
    t.add_argument("--iters", type=positive_int, default=2000, help="iterations")
    t.add_argument("-o", "--output", required=True, help="run folder")
    t.add_argument("--widths", type=positive_int, nargs="+", default=[12, 24, 48, 64], help="U-Net level widths")
    t.add_argument("--input", choices=["capture", "target"], default="capture",
                   help="learn from the aberrated capture (default) or the sharp image")
    t.add_argument("--batch", type=positive_int, default=4, help="batch (default 4)")
    t.add_argument("--crop", type=positive_int, default=128, help="crop size (default 128)")
    t.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (cosine to 1 %%)")
    t.add_argument("--seed", type=int, default=0, help="seed of weights and crops")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    t.add_argument("--checkpoint-every", type=positive_int, default=500, help="iterations between checkpoints")
    t.set_defaults(func=cmd_depth_train)
    return t


def add_commands(sub) -> None:
    q = sub.add_parser("depth", help="depth of a capture: estimate (from its own blur); the depth network: train, "
                                     "export",
                       description="Depth of a capture from its own lens's blur (estimate), and the small "
                                   "metric-depth network on a lens's captures: training and the shipped file.")
    qsub = add_subcommands(q, "depth_command")
    estimate_parser(qsub)
    train_parser(qsub, "train", help="train (or resume) the small depth network on DA2T pairs")
    t = qsub.add_parser("export", help="write a depth run as a shipped .npz (no pickle)")
    add_export_options(t)
    t.set_defaults(func=cmd_depth_export)
