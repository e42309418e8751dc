"""Sensor spectral response: from monochromatic PSFs to RGB PSFs.

An RGB PSF is a weighted sum of monochromatic PSFs traced at W sample
wavelengths::

    PSF_c = sum_i w_c(lambda_i) PSF(lambda_i),   sum_i w_c(lambda_i) = 1

with ``w_c(lambda_i)`` proportional to the channel's relative response
``S_c(lambda_i)`` times the width of the wavelength interval the sample stands
for (see :meth:`SpectralResponse.channel_weights`). The scene is taken to have
a flat (equal-energy) spectrum; each channel is normalised on its own, so the
relative gains of R, G and B (white balance) do not enter.

Default curves
--------------
:func:`default_response` loads ``data/default_rgb_response.csv``: the measured
spectral sensitivities of the **Sony NEX-5N** from the Camera Spectral
Sensitivity Database of Jiang, Liu, Gu and Susstrunk, "What is the space of
spectral sensitivity functions for digital color cameras?", IEEE WACV 2013,
doi:10.1109/WACV.2013.6475015 (http://www.gujinwei.org/research/camspec/db.html).
The numbers are copied unchanged from the database file; on loading, each
channel is max-normalised to 1 (the database has one common scale, green max
= 1). The data cover **400-720 nm in 10 nm steps** (33 samples): the whole
400-700 nm visible band, but nothing below 400 nm or above 720 nm, where the
response is taken as 0 (at 400 nm the measured values are already small: R
1.2 %, G 0.9 %, B 4.2 % of each channel's peak). Peaks: B 450 nm, G 530 nm,
R 590 nm.

User CSV format
---------------
A user response is a small text file read by :func:`load_response`::

    # name: My sensor                 (optional; default: the file name)
    # source: where the numbers are from   (optional; default: the path)
    # any other line starting with # is a comment; blank lines are ignored
    wavelength_nm,r,g,b
    400,0.01,0.05,0.60
    410,0.02,0.07,0.70
    ...

* The header line names the four columns ``wavelength_nm``, ``r``, ``g``,
  ``b`` (case-insensitive, surrounding spaces ignored, any order); it is the
  first line that is neither blank nor a comment.
* One row per wavelength, comma-separated, four numbers a row.
* Wavelengths in nm, strictly increasing, within 300..1100 nm.
* Responses finite and >= 0, in any common or per-channel scale: each channel
  is max-normalised to 1 on loading.
* At least 2 rows, and every channel positive somewhere.

Outside the tabulated range the response is 0. Every error is a
:class:`SpectralFileError` whose message names the file, the line number and
the offending value.
"""
from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from importlib import resources

import numpy as np

from .. import caches
from ..errors import InputRangeError

from ..optics.errors import OpticsError

CHANNELS = ("R", "G", "B")
COLUMNS = ("wavelength_nm", "r", "g", "b")
WAVELENGTH_RANGE_NM = (300.0, 1100.0)
DEFAULT_RESPONSE_FILE = "default_rgb_response.csv"


class SpectralFileError(OpticsError, ValueError):
    """A spectral-response CSV file that breaks the format; names file, line and value."""

    def __init__(self, path, line_number, message, value=None):
        self.path = str(path)
        self.line_number = line_number
        self.value = value
        text = f"{self.path}:{line_number}: {message}"
        if value is not None:
            text += f" (got {value!r})"
        super().__init__(text)


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SpectralResponse:
    """Relative spectral response of a sensor's R, G and B channels.

    ``wavelength_nm`` (M,) strictly increasing, in nm; ``rgb`` (M, 3), >= 0,
    each channel max-normalised to 1 (the constructor normalises whatever it is
    given). Between samples the response is linear, outside them it is 0.
    """

    name: str
    source: str                 # citation of where the numbers come from
    wavelength_nm: np.ndarray   # (M,), strictly increasing, nm
    rgb: np.ndarray             # (M, 3) relative response, >= 0, each channel max 1

    def __post_init__(self):
        wl = np.asarray(self.wavelength_nm, dtype=np.float64)
        rgb = np.asarray(self.rgb, dtype=np.float64)
        if wl.ndim != 1 or wl.size < 2:
            raise InputRangeError("wavelength_nm", f"shape {wl.shape}", "a 1-D array of at least 2 wavelengths")
        if rgb.shape != (wl.size, 3):
            raise InputRangeError("rgb", f"shape {rgb.shape}", f"shape ({wl.size}, 3), one row per wavelength")
        if not np.all(np.isfinite(wl)) or not np.all(np.diff(wl) > 0):
            raise InputRangeError("wavelength_nm", wl.tolist(), "finite and strictly increasing")
        if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
            raise InputRangeError("rgb", "non-finite or negative values", "finite values >= 0")
        peak = rgb.max(axis=0)
        for c in range(3):
            if not peak[c] > 0:
                raise InputRangeError(f"rgb[:, {c}] (channel {CHANNELS[c]})", "all zero",
                                      "some positive response")
        object.__setattr__(self, "wavelength_nm", _readonly(wl))
        object.__setattr__(self, "rgb", _readonly(rgb / peak))

    # -- sampling -----------------------------------------------------------

    def at(self, wavelength_nm) -> np.ndarray:
        """Response at ``wavelength_nm`` (any shape): (..., 3), linear
        interpolation, 0 outside the tabulated range."""
        x = np.asarray(wavelength_nm, dtype=np.float64)
        out = np.stack([np.interp(x, self.wavelength_nm, self.rgb[:, c], left=0.0, right=0.0)
                        for c in range(3)], axis=-1)
        return out

    def channel_weights(self, wavelength_nm) -> np.ndarray:
        """(W, 3) weights of W sample wavelengths; each column sums to 1.

        ``w[i, c]`` is proportional to ``S_c(lambda_i) * d_i``, where ``d_i``
        is the width of the wavelength cell of sample i: the cells are bounded
        by the midpoints between neighbouring (sorted) samples, and the end
        cells reach half a neighbour spacing beyond the end samples. For
        equally spaced samples this is the midpoint rule (all ``d_i`` equal);
        for uneven ones it is the trapezoid rule's interior weights. The
        samples may come in any order (weights follow the given order) but must
        be finite and distinct. One sample gets weight 1 in every channel that
        responds at it. A channel with zero response at every sample raises
        :class:`InputRangeError` naming the channel and the sampled range.
        """
        x = np.asarray(wavelength_nm, dtype=np.float64)
        if x.ndim == 0:
            x = x.reshape(1)
        if x.ndim != 1 or x.size < 1:
            raise InputRangeError("wavelength_nm", f"shape {x.shape}", "a 1-D array of at least 1 wavelength")
        if not np.all(np.isfinite(x)):
            raise InputRangeError("wavelength_nm", x.tolist(), "finite wavelengths in nm")
        order = np.argsort(x, kind="stable")
        xs = x[order]
        if np.any(np.diff(xs) <= 0):
            raise InputRangeError("wavelength_nm", x.tolist(), "distinct wavelengths (no repeats)")
        if xs.size == 1:
            width_sorted = np.ones(1)
        else:
            mid = 0.5 * (xs[1:] + xs[:-1])
            edges = np.concatenate(([xs[0] - (mid[0] - xs[0])], mid, [xs[-1] + (xs[-1] - mid[-1])]))
            width_sorted = np.diff(edges)
        width = np.empty_like(width_sorted)
        width[order] = width_sorted
        w = self.at(x) * width[:, None]
        total = w.sum(axis=0)
        for c in range(3):
            if not total[c] > 0:
                raise InputRangeError(
                    f"wavelength_nm (channel {CHANNELS[c]} of response {self.name!r})",
                    f"{xs.size} sample(s) in {xs[0]:g}..{xs[-1]:g} nm",
                    f"samples where channel {CHANNELS[c]} responds "
                    f"(non-zero only within {self._support(c)}); the channel would be black")
        return w / total

    def _support(self, c: int) -> str:
        nz = np.nonzero(self.rgb[:, c] > 0)[0]
        i0, i1 = nz[0], nz[-1]
        # linear interpolation: positive strictly between the neighbouring zero samples
        lo = self.wavelength_nm[i0 - 1] if i0 > 0 else self.wavelength_nm[0]
        hi = self.wavelength_nm[i1 + 1] if i1 + 1 < self.wavelength_nm.size else self.wavelength_nm[-1]
        return f"{lo:g}..{hi:g} nm"

    def content_hash(self) -> str:
        """sha256 (hex) of the numbers (shape, wavelengths and normalised
        responses as little-endian float64); the name and source do not enter."""
        h = hashlib.sha256()
        h.update(f"spectral-response-v1:{self.wavelength_nm.size}".encode())
        h.update(np.ascontiguousarray(self.wavelength_nm, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.rgb, dtype="<f8").tobytes())
        return h.hexdigest()

    def __eq__(self, other):
        if not isinstance(other, SpectralResponse):
            return NotImplemented
        return (self.name == other.name and self.source == other.source
                and np.array_equal(self.wavelength_nm, other.wavelength_nm)
                and np.array_equal(self.rgb, other.rgb))

    def __hash__(self):
        return hash((self.name, self.source, self.content_hash()))

    def __repr__(self):
        return (f"SpectralResponse(name={self.name!r}, {self.wavelength_nm.size} samples "
                f"{self.wavelength_nm[0]:g}..{self.wavelength_nm[-1]:g} nm)")


# -- files ------------------------------------------------------------------

def _parse_float(text: str, path, line_number: int, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise SpectralFileError(path, line_number, f"{what} is not a number", text) from None
    if not math.isfinite(v):
        raise SpectralFileError(path, line_number, f"{what} is not finite", text)
    return v


def load_response(path) -> SpectralResponse:
    """Read a user spectral response from a CSV file (format: module docstring)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise OpticsError(f"{path}: the spectral response file cannot be read ({e.strerror or e}); "
                          "give a CSV of wavelength_nm,r,g,b") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[:e.start].count(b"\n") + 1
        raise SpectralFileError(path, line, "not UTF-8 text", raw[e.start:e.start + 8]) from None
    return _parse_response(text, path)


def _parse_response(text: str, path) -> SpectralResponse:
    name = None
    source = None
    header_line = None
    index = None          # column index of wavelength_nm, r, g, b
    wl, rows, lines = [], [], []
    last_line = 0
    for line_number, line in enumerate(text.splitlines(), start=1):
        last_line = line_number
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s[1:].strip()
            key, sep, val = body.partition(":")
            if sep and header_line is None:
                key = key.strip().lower()
                if key == "name" and name is None:
                    name = val.strip()
                elif key == "source" and source is None:
                    source = val.strip()
            continue
        fields = [t.strip() for t in s.split(",")]
        if header_line is None:
            names = [t.lower() for t in fields]
            for col in COLUMNS:
                if col not in names:
                    raise SpectralFileError(
                        path, line_number,
                        f"header must name the columns {','.join(COLUMNS)}; column {col!r} is missing", s)
            if len(names) != len(COLUMNS) or len(set(names)) != len(names):
                raise SpectralFileError(
                    path, line_number,
                    f"header must name exactly the columns {','.join(COLUMNS)}, once each", s)
            index = [names.index(col) for col in COLUMNS]
            header_line = line_number
            continue
        if len(fields) != len(COLUMNS):
            raise SpectralFileError(
                path, line_number, f"expected {len(COLUMNS)} comma-separated values, found {len(fields)}", s)
        lam = _parse_float(fields[index[0]], path, line_number, "wavelength_nm")
        lo, hi = WAVELENGTH_RANGE_NM
        if not (lo <= lam <= hi):
            raise SpectralFileError(path, line_number, f"wavelength_nm is outside {lo:g}..{hi:g} nm",
                                    fields[index[0]])
        if wl and not lam > wl[-1]:
            raise SpectralFileError(
                path, line_number,
                f"wavelengths must be strictly increasing; previous row has {wl[-1]:g} nm", fields[index[0]])
        vals = []
        for k, col in enumerate(COLUMNS[1:], start=1):
            v = _parse_float(fields[index[k]], path, line_number, f"response {col}")
            if v < 0:
                raise SpectralFileError(path, line_number, f"response {col} is negative", fields[index[k]])
            vals.append(v)
        wl.append(lam)
        rows.append(vals)
        lines.append(line_number)
    if header_line is None:
        raise SpectralFileError(path, max(last_line, 1),
                                f"no header line {','.join(COLUMNS)} found (empty file?)")
    if len(wl) < 2:
        raise SpectralFileError(path, lines[-1] if lines else header_line,
                                f"at least 2 data rows are needed, found {len(wl)}")
    rgb = np.asarray(rows, dtype=np.float64)
    for c, col in enumerate(COLUMNS[1:]):
        if not np.any(rgb[:, c] > 0):
            raise SpectralFileError(
                path, header_line,
                f"channel {col} is 0 on every row (lines {lines[0]}..{lines[-1]}); "
                "it needs some positive response", col)
    base = os.path.basename(path)
    return SpectralResponse(name=name or os.path.splitext(base)[0], source=source or str(path),
                            wavelength_nm=np.asarray(wl), rgb=rgb)


_DEFAULT: SpectralResponse | None = None


def _forget_default() -> None:
    global _DEFAULT
    _DEFAULT = None


caches.register("default spectral response", _forget_default, lambda: int(_DEFAULT is not None))


def default_response() -> SpectralResponse:
    """The shipped default curves: Sony NEX-5N, Jiang et al. 2013 (see module docstring)."""
    global _DEFAULT
    if _DEFAULT is None:
        ref = resources.files(__package__).joinpath("data", DEFAULT_RESPONSE_FILE)
        with resources.as_file(ref) as p:
            _DEFAULT = load_response(p)
    return _DEFAULT


def visible_wavelengths(n: int, lo_nm: float = 400.0, hi_nm: float = 700.0) -> np.ndarray:
    """``n`` midpoint samples of [lo_nm, hi_nm]: ``lo + (i + 1/2) (hi - lo) / n``.

    n == 1 gives the middle of the band; n < 1 raises InputRangeError.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        if isinstance(n, (float, np.floating)) and float(n).is_integer():
            n = int(n)
        else:
            raise InputRangeError("n", n, "an integer >= 1")
    n = int(n)
    if n < 1:
        raise InputRangeError("n", n, "an integer >= 1")
    lo, hi = float(lo_nm), float(hi_nm)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi):
        raise InputRangeError("band_nm", (lo_nm, hi_nm), "finite 0 < lo_nm < hi_nm")
    step = (hi - lo) / n
    return lo + (np.arange(n) + 0.5) * step
