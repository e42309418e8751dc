"""What the renderers share: the simulator (``render.simulate``) and the
bokeh (``render.bokeh``) both return a :class:`RenderResult`, stop with
:class:`Cancelled`, check their inputs here (image and depth, patch size,
the frame within the sensor, a given library's pixel pitch) and move the
sharp image and its depth onto the sensor (:func:`on_sensor`: the lens's
distortion). The PSFs themselves come from ``psf.sources``.

Units: depths in metres, lengths on the sensor in mm, positions in pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputRangeError
from ..psf.library import PSFLibrary, valid_depth_mask
from ..psf.pitch import SAME_GIVEN_RTOL
from .geometry import ImageGeometry
from .psfmap import PSFMap


class Cancelled(Exception):
    """Raised by a render (``render.bokeh.bokeh``) when its ``cancelled()`` callback returns True."""


@dataclass
class RenderResult:
    """What a simulation or a bokeh render returns; images on the sensor's frame."""

    image: np.ndarray                 # (H, W, 3) float32, linear
    info: dict = field(default_factory=dict)
    sharp: np.ndarray | None = None   # simulate(): the sharp image on the sensor (distorted alike)
    psf_map: PSFMap | None = None
    baseline: np.ndarray | None = None  # LensSimulator with baseline_depth_m: the depth-unaware image
    depth: np.ndarray | None = None   # the depth map on the sensor (NaN where nothing was imaged)


def check_image(image, depth, geometry: ImageGeometry | None = None):
    """(image float32 (H, W, 3), depth float64 (H, W) metres), checked:
    shapes, finite light, and the frame ``geometry`` says if one is given."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("image shape", img.shape, "(H, W, 3)")
    if not np.isfinite(img).all():
        raise InputRangeError("image", "non-finite values", "finite linear RGB")
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != img.shape[:2]:
        raise InputRangeError("depth map shape", d.shape, f"{img.shape[:2]}, the image's")
    if geometry is not None and img.shape[:2] != (geometry.height, geometry.width):
        raise InputRangeError("image shape", img.shape[:2],
                              f"({geometry.height}, {geometry.width}), as its geometry says")
    return img, d


# the warp's interpolation of the sharp image (report simulation-accuracy,
# MOS-S1 at field 0.7: bilinear 62.3 dB, Keys 78.5, Lanczos-3 82.9, cubic
# B-spline 84.8 dB, for 0.42 / 0.90 / 1.86 / 1.38 s at 1280 x 1920)
DEFAULT_INTERPOLATION = "bspline"


def check_patch(patch) -> int:
    """The patch size m (pixels): even, >= 2 (the tent blend takes m / 2 from each side)."""
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)) or patch < 2 or patch % 2:
        raise InputRangeError("patch", patch, "an even number of pixels >= 2 (16 is the paper's)")
    return int(patch)


def check_within_sensor(geometry: ImageGeometry, what: str = "the image") -> None:
    """Refuse a frame whose corners lie beyond the sensor (field > 1), before any work."""
    f = geometry.max_field
    if f > 1.0 + 1e-9:
        raise InputRangeError(
            f"field of {what}'s corner", round(f, 6),
            "<= 1 (the lens's sensor semi-diagonal): the frame is larger than the sensor; for an over-scan "
            "render give the sensor's frame (--sensor-size ROWS COLS, and --axis ROW COL) or the image's "
            "pixel pitch")


def check_flag(name: str, value) -> None:
    """Refuse an on/off option that is not a bool (a truthy string is not a yes)."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputRangeError(name, value, "True or False")


def check_library_pitch(library: PSFLibrary, geometry: ImageGeometry) -> None:
    """A given library must be sampled at the image's pixel pitch (mm)."""
    if not math.isclose(library.pixel_pitch_mm, geometry.pixel_pitch_mm, rel_tol=SAME_GIVEN_RTOL):
        raise InputRangeError("library pixel pitch", library.pixel_pitch_mm,
                              f"{geometry.pixel_pitch_mm:.6g} mm, the image's (open it at that pitch: psf.sources.lens_library)")


def sensor_mapping(distortion):
    """(ideal radius of a real radius, the table's reach in mm, its name) for
    a RadialDistortion table, a ChiefRayMap (the widest ideal radius over
    its depths: what a frame's sources need at most) or the identity for None."""
    from .distortion import ChiefRayMap

    if distortion is None:
        return (lambda r: r), math.inf, "identity"
    if isinstance(distortion, ChiefRayMap):
        return distortion.widest_ideal_from_real, distortion.reach_real_mm, "chief-ray map"
    return distortion.ideal_from_real, distortion.reach_real_mm, "real-height"


# passes of the depth-dependent warp: each reads the depth its pixels came
# from under the previous pass's positions (the first: the focus distance's);
# two settle every pixel off a depth edge (the chief ray's depth dependence is
# under a pixel: 0.54 px of 100 um at the Sonnar's corner between 1.5 and 6 m)
DEPTH_WARP_PASSES = 2


def _depth_codes(depth) -> np.ndarray:
    # depths travel as finite codes (nearest copies them): -1 infinity, -2 invalid
    d = np.asarray(depth, dtype=np.float64)
    return np.where(np.isinf(d) & (d > 0), -1.0, np.where(valid_depth_mask(d), d, -2.0))


def _code_diopters(code: np.ndarray, invalid_diopters: float) -> np.ndarray:
    """Diopters (1/m) of warped depth codes: 0 for infinity, ``invalid_diopters`` where invalid."""
    safe = np.where(code > 0, code, 1.0)
    return np.where(code > 0, 1.0 / safe, np.where(code == -1.0, 0.0, invalid_diopters))


def on_sensor(image, depth, lens, geometry: ImageGeometry, *, source_geometry: ImageGeometry | None = None,
              distortion=None, interpolation: str = DEFAULT_INTERPOLATION):
    """An ideal (pinhole) image and its depth map moved to where the lens puts
    them on the sensor: (image (H, W, C) float32, depth (H, W) float64, valid
    (H, W) bool) on ``geometry``'s grid.

    distortion: a ChiefRayMap (the lens's real chief rays at its focus, per
    depth: each pixel moved by the map at the depth it shows), a
    RadialDistortion table (one depth), or None for none (then the output is
    the source resampled onto ``geometry``: a crop of an over-scan render,
    say). The image is interpolated with ``interpolation``; the depth map by
    its nearest sample (a blend of two depths is no depth). Pixels whose
    source lies outside the input are 0 with depth NaN (invalid)."""
    from .distortion import ChiefRayMap, _warp

    src = source_geometry or geometry
    if distortion is None and src == geometry:
        d = np.asarray(depth, dtype=np.float64)
        return np.asarray(image, np.float32), d, np.ones(d.shape, bool)
    radius, reach, table = sensor_mapping(distortion)
    code = _depth_codes(depth)
    if isinstance(distortion, ChiefRayMap):
        focus = distortion.focus_m
        at_focus = 0.0 if focus is None or math.isinf(focus) else 1.0 / focus
        diopters = at_focus
        for _ in range(DEPTH_WARP_PASSES):
            dep, _ = _warp(code, geometry, src, lambda r, dio=diopters: distortion.ideal_from_real(r, dio),
                           "the sensor", reach, table, interpolation="nearest")
            diopters = _code_diopters(dep, at_focus)
        radius = lambda r: distortion.ideal_from_real(r, diopters)     # noqa: E731
    img, valid = _warp(image, geometry, src, radius, "the sensor", reach, table, interpolation=interpolation)
    # higher-order interpolation rings below 0 at edges; light is never negative
    np.maximum(img, 0.0, out=img)
    dep, _ = _warp(code, geometry, src, radius, "the sensor", reach, table, interpolation="nearest")
    dep = dep.astype(np.float64)
    dep = np.where(dep == -1.0, np.inf, np.where(valid & (dep > 0), dep, np.nan))
    return img, dep, valid
