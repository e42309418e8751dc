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

from . import bench, correct, dacn, dataset, depth, info, lens, olf, psf, render
from .common import UNITS, error_words, one_line, show_warning
from .files import attach, job_files


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dcdi", description=__doc__.split("\n\n")[0] + " " + UNITS,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in (lens, psf, render, correct, info, olf, dacn, depth, dataset, bench):
        group.add_commands(sub)
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
