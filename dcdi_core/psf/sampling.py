"""How finely an image needs its PSFs sampled: the fields' step and the
focus distance's step, both in the image's own pixels.

A PSF library samples fields 0 to 1 (the sensor's semi-diagonal) and
interpolates between them; how far apart two samples may be depends on the
image, not the lens alone: a PSF's structure that moves by s mm between two
fields moves by s / pitch pixels, so an image at a coarser pitch (a 480 x
270 viewport preview against a 1920 x 1080 render) needs proportionally
fewer fields for the same error in its pixels. :func:`field_grid` keeps
the fields at most ``step_px`` image pixels apart (never more fields than
the source's grid holds).

A refocused lens's PSFs are made per focus distance; two focus distances
whose defocus blurs differ by less than a fraction of a pixel give the same
picture. :func:`snap_focus` rounds a focus distance down, in diopters
(towards infinity: a source's learned focus range ends there, so the
rounded focus stays inside it), to a grid uniform in diopters whose step
changes no depth's blur diameter by more than ``tolerance_px`` pixels (the thin-lens blur: diameter = entrance pupil x
focal length x |1/depth - 1/focus|, the paraxial values), so that the
frames of a focus pull or an animation whose focus moves within that bound
share one set of PSFs.

Units: pixel pitch in mm, distances in metres, diopters in 1/m.
"""
from __future__ import annotations

import math
from dataclasses import replace

from ..errors import InputRangeError
from .library import LibraryGrid

MIN_FIELDS = 8           # a grid never coarser than this: the corners' PSFs differ from the axis's


def _check_positive(name: str, value) -> float:
    v = float(value)
    if not (v > 0 and math.isfinite(v)):
        raise InputRangeError(name, value, "> 0 and finite")
    return v


def field_grid(grid: LibraryGrid | None, semi_diagonal_mm: float, pixel_pitch_mm: float,
               step_px: float | None) -> LibraryGrid | None:
    """``grid`` (default: ``LibraryGrid()``) with at most as many fields as
    keep neighbouring fields ``step_px`` image pixels apart on a sensor of
    semi-diagonal ``semi_diagonal_mm`` sampled at ``pixel_pitch_mm`` (at
    least MIN_FIELDS; never more than ``grid``'s). ``step_px`` None: ``grid``
    unchanged (None stays None: the source's own grid)."""
    if step_px is None:
        return grid
    step = _check_positive("field_step_px", step_px)
    base = grid or LibraryGrid()
    span_px = _check_positive("semi_diagonal_mm", semi_diagonal_mm) / _check_positive("pixel_pitch_mm",
                                                                                     pixel_pitch_mm)
    n = max(MIN_FIELDS, math.ceil(span_px / step) + 1)
    return base if n >= base.n_fields else replace(base, n_fields=n)


def blur_px_per_diopter(lens, pixel_pitch_mm: float) -> float:
    """The thin-lens defocus blur's diameter, image pixels, per diopter
    between a depth and the focus: entrance pupil diameter x focal length
    (paraxial) / pitch."""
    from ..optics import paraxial
    fo = paraxial.first_order(lens)
    efl = abs(float(fo.effective_focal_length_mm))
    epd = efl / abs(float(fo.f_number))
    return epd * efl / 1000.0 / _check_positive("pixel_pitch_mm", pixel_pitch_mm)


def focus_step_diopters(lens, pixel_pitch_mm: float, tolerance_px: float) -> float:
    """The focus grid's step (diopters): a step moves the focus by at most
    ``tolerance_px`` pixels of blur diameter at any depth."""
    return _check_positive("focus_tolerance_px", tolerance_px) / blur_px_per_diopter(lens, pixel_pitch_mm)


def snap_focus(lens, focus_m, pixel_pitch_mm: float, tolerance_px: float | None):
    """``focus_m`` (metres, or inf, or None / a word: returned unchanged)
    rounded down in diopters to a point of :func:`focus_step_diopters`' grid
    (diopter 0, infinity, is one): at most ``tolerance_px`` pixels of blur
    diameter away, never nearer than asked; ``tolerance_px`` None: unchanged."""
    if tolerance_px is None or focus_m is None or isinstance(focus_m, str):
        return focus_m
    f = float(focus_m)
    if not f > 0:
        return focus_m                  # the request's own check names it
    step = focus_step_diopters(lens, pixel_pitch_mm, tolerance_px)
    d = math.floor((1.0 / f) / step * (1.0 + 1e-12)) * step      # a focus on the grid stays put
    return math.inf if d <= 0 else 1.0 / d


__all__ = ["field_grid", "snap_focus", "focus_step_diopters", "blur_px_per_diopter", "MIN_FIELDS"]
