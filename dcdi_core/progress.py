"""Progress bars for long steps, through tqdm when it is there.

Every long step of the engine reports through a plain callback
``progress(done, total)`` (the PSF build after each batch of PSFs); this
module makes such callbacks for a terminal. tqdm is imported lazily: the
engine imports and runs without it (Blender's own Python has numpy but no
tqdm; the add-on passes its own callbacks), and without it, or when the
stream is not a terminal (a log file, a pipe, a test), progress is silent.
"""
from __future__ import annotations

import sys


def _tqdm():
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm


def enabled(stream=None) -> bool:
    """Whether bars are drawn on ``stream`` (standard error by default): only
    on a terminal, and only with tqdm installed."""
    stream = sys.stderr if stream is None else stream
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return bool(tty) and _tqdm() is not None


class Bar:
    """A callback ``bar(done, total)`` drawing a tqdm bar; a new bar starts
    when ``total`` changes or ``done`` goes back (a second pass, as when the
    kernel is refitted). Call :meth:`close` at the end (or let the last
    ``done == total`` close it)."""

    def __init__(self, label: str, unit: str = "PSF", stream=None):
        self.label, self.unit = label, unit
        self.stream = sys.stderr if stream is None else stream
        self._bar = None
        self._total = None
        self._done = 0

    def __call__(self, done: int, total: int) -> None:
        if self._bar is None or total != self._total or done < self._done:
            self.close()
            tqdm = _tqdm()
            self._bar = tqdm(total=total, desc=self.label, unit=self.unit, file=self.stream, leave=True,
                             dynamic_ncols=True)
            self._total, self._done = total, 0
        self._bar.update(done - self._done)
        self._done = done
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def psf_progress(label: str, stream=None):
    """A progress callback for a PSF build labelled ``label``, or None (silence)
    when ``stream`` (standard error) is not a terminal or tqdm is missing."""
    return Bar(label, "PSF", stream) if enabled(stream) else None


def bar(label: str, unit: str, stream=None):
    """A progress callback ``(done, total)`` with its own unit (layers,
    samples), or None (silence) off a terminal or without tqdm."""
    return Bar(label, unit, stream) if enabled(stream) else None


class Steps:
    """The named steps of a command, one line each on a terminal as a step
    starts ("dcdi simulate: convolution"), with the seconds of the whole at
    the end; silent elsewhere. For steps without a count of their own."""

    def __init__(self, label: str, stream=None):
        import time

        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.on = enabled(stream)
        self._t0 = time.perf_counter()

    def start(self, name: str) -> None:
        if self.on:
            self.stream.write(f"{self.label}: {name}\n")
            self.stream.flush()

    def done(self) -> None:
        import time

        if self.on:
            self.stream.write(f"{self.label}: done in {time.perf_counter() - self._t0:.1f} s\n")
            self.stream.flush()


class StageBars:
    """``progress(stage, done, total)`` of an application job (``app.Control``)
    drawn on a terminal: one bar per stage with a count ('PSFs', 'depth
    layers', windows, tiles), silent elsewhere."""

    UNITS = {"PSFs": "PSF", "depth layers": "layer", "deconvolving": "window", "correcting": "tile"}

    def __init__(self, label: str, stream=None):
        self.label, self.stream = label, stream
        self._bars: dict = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if done == 0 and total <= 1 and stage not in self._bars:
            return                                  # a stage starting: its count comes with its first step
        if stage not in self._bars:
            self._bars[stage] = bar(f"{self.label}: {stage}", self.UNITS.get(stage, "step"), self.stream)
        b = self._bars[stage]
        if b is not None:
            b(done, total)
