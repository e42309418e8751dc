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
    from ..names import TerminalStream
    args = build_parser().parse_args(argv)
    from ..signals import stop_code, stop_on_signals
    with warnings.catch_warnings(), stop_on_signals(), _terminal_safe(TerminalStream):
        warnings.showwarning = show_warning          # one line each, no source line
        try:
            files = job_files(args)          # every path it reads and writes, checked before any work
            if files is None:
                code = args.func(args)
            else:
                files.check()
                with files.together():       # its output files appear together, or none does
                    code = args.func(args)
            sys.stdout.flush()               # here, where a reader gone away is answered (not at the exit)
            return code
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
        except BrokenPipeError:                  # the reader went away (`dcdi lens list | head -n 1`): quietly
            _quiet_stdout()
            return BROKEN_PIPE_EXIT


BROKEN_PIPE_EXIT = 141      # as a process killed by SIGPIPE: 128 + 13


def _quiet_stdout() -> None:
    """Point stdout at the null device, so that the interpreter's flush at
    exit does not meet the closed pipe again (and print a traceback)."""
    import os
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.__stdout__.fileno())
    except (OSError, ValueError, AttributeError):
        pass


class _terminal_safe:
    """While a command runs, its stdout and stderr escape every control
    character but line breaks and tabs (``names.TerminalStream``): a lens
    name or a record's field from someone's file cannot drive the terminal."""

    def __init__(self, stream_type):
        self.stream_type = stream_type

    def __enter__(self):
        self.saved = sys.stdout, sys.stderr
        sys.stdout, sys.stderr = self.stream_type(sys.stdout), self.stream_type(sys.stderr)

    def __exit__(self, *exc):
        sys.stdout, sys.stderr = self.saved
        return False


__all__ = ["main", "build_parser"]
