"""`dcdi dataset stats`: what a data set's frames hold (``app.dataset_stats``):
texture, depth mix, clipping, and how much blur each lens leaves to correct."""
from __future__ import annotations

import sys
from pathlib import Path

from .common import add_subcommands, positive_int


def cmd_dataset_stats(args) -> int:
    from ..app.dataset_stats import DatasetReportOptions, run_report
    options = DatasetReportOptions(lenses=tuple(args.lens or ("mos-s1", "mos-s2")), frames=args.frames,
                                   seed=args.seed)
    run_report(args.dirs, options, args.out, log=lambda t: print(t, file=sys.stderr, flush=True))
    print((Path(args.out) / "report.md").read_text(encoding="utf-8"), end="")
    return 0


def add_commands(sub) -> None:
    q = sub.add_parser("dataset", help="a data set of factory frames: what it holds")
    dsub = add_subcommands(q, "dataset_command")
    r = dsub.add_parser("stats", help="what factory frames hold, per recipe: texture (high-frequency share), "
                                      "depth mix, clipping, and the share of 128 px crops whose capture through "
                                      "a lens is already above 40 dB")
    r.add_argument("dirs", nargs="+", metavar="DIR", help="one or more factory folders (frames grouped by recipe "
                                                          "across them)")
    r.add_argument("--lens", action="append", default=None, metavar="LENS",
                   help="a lens id for the blur measure (repeat for several; default mos-s1 and mos-s2)")
    r.add_argument("--frames", type=positive_int, default=None,
                   help="at most this many frames per recipe, chosen evenly (default all)")
    r.add_argument("--seed", type=int, default=0, help="the frames' random places on the sensor (default 0)")
    r.add_argument("--out", default="out/dataset-stats", help="folder for report.md, results.json and a picture "
                                                              "per recipe (default out/dataset-stats)")
    r.set_defaults(func=cmd_dataset_stats)
