"""`dcdi dataset stats`: what a data set's frames hold (``app.dataset_stats``):
texture, depth mix, clipping, and how much blur each lens leaves to correct.
`dcdi dataset textures`: a folder of textures with photographs' statistics
(``dataset.natural``) for any ``--textures DIR``."""
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


def cmd_dataset_textures(args) -> int:
    import json

    from ..dataset.natural import write_textures
    paths = write_textures(args.out, args.count, args.seed, args.size,
                           progress=lambda i, n: print(f"\rtextures {i}/{n}", end="" if i < n else "\n",
                                                       file=sys.stderr, flush=True))
    print(json.dumps({"out": str(args.out), "textures": len(paths), "seed": args.seed, "size_px": args.size}))
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
    t = dsub.add_parser("textures", help="a folder of seeded textures with photographs' statistics (1/f^a spectra "
                                         "with a drawn per texture, edges, natural colours; docs/depth.md) for "
                                         "the factory's --textures DIR")
    t.add_argument("-o", "--out", required=True, metavar="DIR", help="the folder (made if missing; existing "
                                                                     "natural-NNNN.png files are never overwritten)")
    t.add_argument("--count", type=positive_int, default=64, help="how many textures (default 64)")
    t.add_argument("--size", type=positive_int, default=512,
                   help="each texture's side, 16-8192 px (default 512); one texture takes about 160 bytes a "
                        "pixel while it is made: 42 MB at 512, 10.7 GB at 8192, refused where it would not fit")
    t.add_argument("--seed", type=int, default=0, help="texture i is drawn from (seed, i) (default 0)")
    t.set_defaults(func=cmd_dataset_textures)
