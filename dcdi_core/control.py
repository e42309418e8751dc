"""How a front end follows and stops a job: progress by stage, and cancel.

A job calls ``progress(stage, done, total)`` as it goes (stages: 'PSFs',
'depth layers', 'simulating', 'deconvolving', 'correcting', ...) and asks
``cancelled()`` at its safe points (between PSF bins, depth layers,
deconvolution windows, network tiles); when it returns True the job raises
:class:`Cancelled` and leaves nothing half-written (jobs write no files).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from .errors import DcdiError


class Cancelled(DcdiError):
    """The front end asked the job to stop (Esc in Blender, Ctrl-C)."""


@dataclass(frozen=True)
class Control:
    """``progress(stage, done, total)``, ``cancelled() -> bool`` and
    ``note(line)`` (a line for the user as soon as it is known: which PSFs
    serve the job, which correction runs and why), each optional."""

    progress: Callable[[str, int, int], None] | None = None
    cancelled: Callable[[], bool] | None = None
    note: Callable[[str], None] | None = None

    def say(self, line: str) -> None:
        if self.note is not None:
            self.note(line)

    def check(self) -> None:
        """Raise :class:`Cancelled` when the front end asked to stop."""
        if self.cancelled is not None and self.cancelled():
            raise Cancelled("cancelled")

    def report(self, stage: str, done: int = 0, total: int = 1) -> None:
        self.check()
        if self.progress is not None:
            self.progress(stage, int(done), int(total))

    def counter(self, stage: str):
        """A ``progress(done, total)`` for the engine's loops (PSF bins,
        layers, windows, tiles) reporting ``stage`` and checking cancel."""
        def report(done, total):
            self.report(stage, done, max(int(total), 1))
        return report
