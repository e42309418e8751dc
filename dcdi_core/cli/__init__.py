"""The `dcdi` command.

Units everywhere: lengths of lenses in millimetres, depths (object distances
from the lens's first vertex) in metres (`inf` for infinity), wavelengths in
nanometres, angles in degrees, fields as normalised image height (1 = sensor
semi-diagonal).

Grammar: noun, then verb (`dcdi lens info`, `dcdi dacn train`); the user's
verbs of the pipeline (`dcdi simulate`, `bokeh`, `correct`, `dof`) stand at
the top. One module per command group; the handlers only turn options into
the engine's calls.
"""
from __future__ import annotations

import argparse
import sys

from . import dacn, depth, info, lens, olf, pipeline, psf, render, reports
from .common import UNITS, deprecated, error_words, one_line, show_warning
from .files import attach, job_files

# old spelling -> new, kept for one release (a note on stderr says so)
DEPRECATED = {"dcdi train dacn": "dcdi dacn train", "dcdi train depth": "dcdi depth train",
              "dcdi eval": "dcdi dacn eval"}


def _add_deprecated(sub) -> None:
    """The old spellings, hidden from the help (no ``help=``), each a note away from its new one."""
    q = sub.add_parser("train", description="Deprecated: use `dcdi dacn train` or `dcdi depth train`.")
    tsub = q.add_subparsers(dest="train_command", required=True, metavar="NETWORK")
    deprecated(dacn.train_parser(tsub, "dacn"), DEPRECATED["dcdi train dacn"])
    deprecated(depth.train_parser(tsub, "depth"), DEPRECATED["dcdi train depth"])
    deprecated(dacn.eval_parser(sub, "eval"), DEPRECATED["dcdi eval"])


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dcdi", description=__doc__.split("\n\n")[0] + " " + UNITS,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in (lens, psf, render, pipeline, info, olf, dacn, depth, reports):
        group.add_commands(sub)
    _add_deprecated(sub)
    attach(p)
    return p


OUT_OF_MEMORY = ("out of memory: the work did not fit in this machine's memory; lower --rays (memory grows as its "
                 "square), --wavelengths or --kernel, or use a smaller image")


def main(argv=None) -> int:
    """The `dcdi` command: exit 0 on success, 2 with one line on stderr for any
    error a user can cause (a DcdiError, or memory running out); anything
    else is a bug and keeps its traceback."""
    import warnings

    from ..errors import DcdiError
    args = build_parser().parse_args(argv)
    new = getattr(args, "deprecated_for", None)
    if new is not None:
        old = next(k for k, v in DEPRECATED.items() if v == new)
        print(f"dcdi: note: '{old}' is deprecated and goes in the next release; use '{new}'", file=sys.stderr)
    from ..signals import stop_code, stop_on_signals
    with warnings.catch_warnings(), stop_on_signals():
        warnings.showwarning = show_warning          # one line each, no source line
        try:
            files = job_files(args)          # every path it reads and writes, checked before any work
            if files is None:
                return args.func(args)
            files.check()
            with files.together():           # its output files appear together, or none does
                return args.func(args)
        except DcdiError as e:
            print(f"dcdi: error: {one_line(e.in_words(error_words(args)))}", file=sys.stderr)
            return 2
        except MemoryError:
            print(f"dcdi: error: {OUT_OF_MEMORY}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as e:           # SIGINT or SIGTERM: this run's temporaries are gone already
            code, word = stop_code(e)
            print(f"dcdi: {word}", file=sys.stderr)
            return code


__all__ = ["main", "build_parser"]
