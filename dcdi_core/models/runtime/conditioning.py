"""What a correction network is told besides the pixels (numpy; the same
code for training crops and for inference, so the two never drift apart).

Field: two maps, (down, right) offset of each pixel centre from the optical
axis in units of the sensor's semi-diagonal, so the corner of the full
sensor is at length 1 whatever the pixel pitch. The PSF of a rotationally
symmetric lens at a pixel depends on this vector alone (its length: the
field; its direction: the PSF's orientation); a crop's maps are those of its
own pixels, not of the frame's centre.

Flips and rotations (``augment_field``): a rotated crop of a rotationally
symmetric lens is a crop at the rotated field position, so the maps are
moved with the pixels *and* their vectors are rotated alike; afterwards the
maps are again the offsets of the pixels of a (virtual) sensor: the down
component grows by one pixel's step per row, the right one per column.

Depth: ``depth_encoding.encode_depth`` (``diopter``: the same absolute
scale for every crop and image).
"""
from __future__ import annotations

import numpy as np

from ...errors import InputRangeError


def field_maps(center_px, pixel_pitch_mm: float, semi_diagonal_mm: float, rows, cols) -> np.ndarray:
    """(2, len(rows), len(cols)) float32: (down, right) offsets of the pixels
    at ``rows`` x ``cols`` (1-D pixel indices of the image) from the axis at
    ``center_px`` (row, col), over the semi-diagonal (dimensionless)."""
    if not (pixel_pitch_mm > 0 and semi_diagonal_mm > 0):
        raise InputRangeError("pixel pitch, semi-diagonal", (pixel_pitch_mm, semi_diagonal_mm), "> 0 mm")
    step = pixel_pitch_mm / semi_diagonal_mm
    down = (np.asarray(rows, np.float64) - center_px[0]) * step
    right = (np.asarray(cols, np.float64) - center_px[1]) * step
    out = np.empty((2, down.size, right.size), np.float32)
    out[0] = down[:, None]
    out[1] = right[None, :]
    return out


def geometry_field_maps(geometry, r0: int = 0, c0: int = 0, h: int | None = None, w: int | None = None):
    """``field_maps`` of the h x w window at (r0, c0) of an image with
    ``render.geometry.ImageGeometry`` ``geometry`` (default: all of it)."""
    h = geometry.height - r0 if h is None else h
    w = geometry.width - c0 if w is None else w
    return field_maps(geometry.center_px, geometry.pixel_pitch_mm, geometry.semi_diagonal_mm,
                      np.arange(r0, r0 + h), np.arange(c0, c0 + w))


def augment_field(maps: np.ndarray, k: int) -> np.ndarray:
    """The field maps (2, H, W) of a crop turned by ``data.augment``'s
    transform k (0..7: k % 4 quarter turns counter-clockwise, then a
    left-right flip if k >= 4): moved like the pixels, vectors turned."""
    down, right = maps[0], maps[1]
    for _ in range(k % 4):
        # np.rot90 counter-clockwise: the pixel at (r, c) goes to (W-1-c, r);
        # its offset (down, right) becomes (-right, down)
        down, right = np.rot90(-right), np.rot90(down)
    if k >= 4:
        down, right = down[:, ::-1], -right[:, ::-1]
    return np.ascontiguousarray(np.stack([down, right]), dtype=np.float32)
