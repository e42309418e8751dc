"""Where an image's pixels lie on the lens's sensor.

Pixel centres sit at integer (row, col) coordinates; row 0 is the top of the
image, col 0 its left edge. Sensor lengths are in millimetres. The optical
axis is at ``center_px`` (fractional pixel coordinates); field 1.0 is the
lens's sensor semi-diagonal (docs/design.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputRangeError


def _size(name, v) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise InputRangeError(name, v, "an integer >= 1 (pixels)")
    return int(v)


def _positive(name, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(v) or v <= 0:
        raise InputRangeError(name, v, "a finite number > 0 (mm)")
    return float(v)


@dataclass(frozen=True)
class ImageGeometry:
    """How an image's pixel grid lies on the lens's sensor (mm).

    ``pixel_pitch_mm`` is the size of one image pixel on the sensor,
    ``center_px`` the (row, col) of the optical axis in pixels (pixel centres
    at integers), ``semi_diagonal_mm`` the lens's sensor semi-diagonal
    (field 1.0).
    """

    height: int
    width: int
    pixel_pitch_mm: float
    center_px: tuple[float, float]
    semi_diagonal_mm: float

    def __post_init__(self):
        _size("height", self.height)
        _size("width", self.width)
        _positive("pixel_pitch_mm", self.pixel_pitch_mm)
        _positive("semi_diagonal_mm", self.semi_diagonal_mm)
        c = self.center_px
        if (not isinstance(c, (tuple, list)) or len(c) != 2
                or not all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
                           and math.isfinite(x) for x in c)):
            raise InputRangeError("center_px", c, "(row, col), two finite numbers (pixels)")
        object.__setattr__(self, "center_px", (float(c[0]), float(c[1])))

    @classmethod
    def full_sensor(cls, lens, height: int, width: int) -> "ImageGeometry":
        """The image spans the sensor's full diagonal (outer corners of the
        corner pixels at field 1): pitch = 2 sd / hypot(H, W), axis at the
        image centre. A resized image keeps its field geometry this way."""
        h, w = _size("height", height), _size("width", width)
        sd = _positive("lens.sensor.semi_diagonal_mm", lens.sensor.semi_diagonal_mm)
        return cls(h, w, 2.0 * sd / math.hypot(h, w), ((h - 1) / 2.0, (w - 1) / 2.0), sd)

    @classmethod
    def from_pixel_pitch(cls, lens, height: int, width: int, pixel_pitch_mm: float,
                         center_px: tuple[float, float] | None = None) -> "ImageGeometry":
        """An image sampled at ``pixel_pitch_mm`` (a crop, or a differently
        sampled image); the axis at ``center_px`` (row, col), by default the
        image centre."""
        h, w = _size("height", height), _size("width", width)
        pitch = _positive("pixel_pitch_mm", pixel_pitch_mm)
        sd = _positive("lens.sensor.semi_diagonal_mm", lens.sensor.semi_diagonal_mm)
        c = ((h - 1) / 2.0, (w - 1) / 2.0) if center_px is None else tuple(center_px)
        return cls(h, w, pitch, c, sd)

    def crop(self, rows: slice, cols: slice) -> "ImageGeometry":
        """The geometry of the box (``rows``, ``cols``: slices with a start and
        a stop, in pixels) of this frame: same pitch, the axis moved with it."""
        return replace(self, height=rows.stop - rows.start, width=cols.stop - cols.start,
                       center_px=(self.center_px[0] - rows.start, self.center_px[1] - cols.start))

    # The offsets are written centre - position (not the reverse) so that on
    # the axis they are +0.0, never -0.0: atan2(-0.0, -0.0) would be -pi.
    def _offsets(self, rows, cols):
        r = np.asarray(rows, dtype=np.float64)
        c = np.asarray(cols, dtype=np.float64)
        return self.center_px[0] - r, self.center_px[1] - c

    def radius_mm(self, rows, cols) -> np.ndarray:
        """Distance (mm) on the sensor from the optical axis to the pixel
        positions (rows, cols): arrays (broadcast together) or scalars."""
        up, left = self._offsets(rows, cols)
        return np.hypot(up, left) * self.pixel_pitch_mm

    def field(self, rows, cols) -> np.ndarray:
        """Normalised image height: ``radius_mm / semi_diagonal_mm``."""
        return self.radius_mm(rows, cols) / self.semi_diagonal_mm

    def azimuth(self, rows, cols) -> np.ndarray:
        """Angle (radians, in (-pi, pi]) of the outward radial direction from
        the axis to (rows, cols), measured from the image's "up" direction
        (decreasing row) and counter-clockwise as seen on screen: up = 0,
        left = pi/2, down = pi, right = -pi/2. 0 on the axis."""
        up, left = self._offsets(rows, cols)
        a = np.arctan2(left, up)
        return np.where((up == 0) & (left == 0), 0.0, a)

    @property
    def max_field(self) -> float:
        """Largest field of any pixel centre (at one of the four corners)."""
        r = np.array([0.0, self.height - 1.0])
        c = np.array([0.0, self.width - 1.0])
        return float(self.field(r[:, None], c[None, :]).max())
