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


def train_parser(subparsers, name: str, **kw):
    """The parser of `depth train` (also the old spelling `train depth`)."""
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
    q = sub.add_parser("depth", help="the depth network: train, export",
                       description="The small metric-depth network on a lens's captures: training and the "
                                   "shipped file.")
    qsub = add_subcommands(q, "depth_command")
    train_parser(qsub, "train", help="train (or resume) the small depth network on DA2T pairs")
    t = qsub.add_parser("export", help="write a depth run as a shipped .npz (no pickle)")
    add_export_options(t)
    t.set_defaults(func=cmd_depth_export)
