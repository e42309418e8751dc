"""The pinhole camera that frames like a lens, and planar depth (docs/design.md).

A renderer such as Blender draws an all-in-focus image through a pinhole;
the lens's blur and distortion are added afterwards from its PSFs. For the
two to line up the pinhole must see what the lens sees:

- it sits at the lens's entrance pupil (the centre of projection of the
  object-space chief rays), ``entrance_pupil_mm`` behind the first vertex;
- its focal length is the lens's paraxial effective focal length (EFL);
- its sensor is the image's rectangle on the lens's sensor when the image
  spans the sensor's full diagonal (``ImageGeometry.full_sensor``), so the
  pinhole's diagonal field of view is 2 atan(semi-diagonal / EFL).

Depth is planar (along the optical axis, as Blender's Z pass) in metres
from the lens's first vertex; the renderer's Z is planar from the pinhole,
i.e. from the entrance pupil. Lengths on the sensor and in the lens are in
millimetres; scene lengths are in the renderer's units, turned into metres
by ``metres_per_unit`` (Blender's unit scale). No bpy here: Blender code
copies the values of :meth:`PinholeCamera.blender_camera_settings`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputRangeError
from ..optics.paraxial import first_order
from .geometry import ImageGeometry

# Cycles writes 1e10 for the world background: a Z at or beyond this (scene
# units) is infinity.
BLENDER_BACKGROUND_Z = 1e9

# Blender's smallest camera sensor width / height and focal length, mm:
# measured with pip bpy 5.0.1, ``bpy.data.cameras.new('x').sensor_width = 0.3``
# reads back 1.0 (as do sensor_height and lens; their RNA hard_min is 1.0).
BLENDER_MIN_SENSOR_MM = 1.0
BLENDER_MIN_FOCAL_LENGTH_MM = 1.0


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole that frames an H x W image like the lens (lengths in mm).

    ``focal_length_mm`` is the lens's paraxial EFL; ``sensor_width_mm`` x
    ``sensor_height_mm`` the image's size on the lens's sensor;
    ``entrance_pupil_mm`` where the pinhole sits: the entrance pupil's
    position behind the lens's first vertex (negative: in front of it);
    ``height`` x ``width`` the image in pixels.
    """

    focal_length_mm: float
    sensor_width_mm: float
    sensor_height_mm: float
    entrance_pupil_mm: float
    height: int
    width: int

    @classmethod
    def for_lens(cls, lens, height: int, width: int) -> "PinholeCamera":
        """The pinhole of ``lens`` for an image of ``height`` x ``width`` px
        that spans the lens's sensor diagonal."""
        fo = first_order(lens)
        efl = float(fo.effective_focal_length_mm)
        if not (math.isfinite(efl) and efl > 0):
            raise InputRangeError(f"{lens.path}: effective focal length (mm)", efl,
                                  "> 0 (a lens that forms a real image of distant objects)")
        geom = ImageGeometry.full_sensor(lens, height, width)
        return cls(efl, geom.width * geom.pixel_pitch_mm, geom.height * geom.pixel_pitch_mm,
                   float(fo.entrance_pupil_position_mm), geom.height, geom.width)

    @property
    def diagonal_field_of_view_deg(self) -> float:
        """Full diagonal angle of view, degrees: 2 atan(sensor diagonal / 2 f)."""
        diagonal = math.hypot(self.sensor_width_mm, self.sensor_height_mm)
        return math.degrees(2.0 * math.atan(diagonal / (2.0 * self.focal_length_mm)))

    def blender_scale(self, min_sensor_mm: float = BLENDER_MIN_SENSOR_MM,
                      min_focal_length_mm: float = BLENDER_MIN_FOCAL_LENGTH_MM) -> float:
        """The factor (>= 1) by which focal length and sensor are both
        enlarged for Blender: the smallest that brings the sensor's width and
        height to ``min_sensor_mm`` and the focal length to
        ``min_focal_length_mm`` or more. 1 when the camera fits as it is."""
        return max(1.0, min_sensor_mm / min(self.sensor_width_mm, self.sensor_height_mm),
                   min_focal_length_mm / self.focal_length_mm)

    def blender_camera_settings(self, min_sensor_mm: float = BLENDER_MIN_SENSOR_MM,
                                min_focal_length_mm: float = BLENDER_MIN_FOCAL_LENGTH_MM) -> dict:
        """The values of a Blender camera (``bpy.types.Camera``) that frames
        like this pinhole, keyed by Blender's property names: ``lens`` and
        ``sensor_width`` / ``sensor_height`` (mm), ``sensor_fit``
        ("HORIZONTAL": the sensor width spans the render's width).

        Blender clamps a sensor side and the focal length to at least 1 mm
        (BLENDER_MIN_SENSOR_MM): a small lens (the double Gauss's sensor is
        0.36 mm across) would silently get a much wider view. A pinhole's
        projection depends only on the ratio sensor / focal length, so both
        are scaled by :meth:`blender_scale` instead: the field of view, and so
        the image, stay the lens's. (Blender's own depth of field, unused
        here, would change with the focal length; the lens's blur is added
        from its PSFs.)"""
        s = self.blender_scale(min_sensor_mm, min_focal_length_mm)
        return {"lens": s * self.focal_length_mm, "sensor_width": s * self.sensor_width_mm,
                "sensor_height": s * self.sensor_height_mm, "sensor_fit": "HORIZONTAL"}


def depth_from_planar_z(z, entrance_pupil_mm: float, metres_per_unit: float = 1.0,
                        background_z: float = BLENDER_BACKGROUND_Z) -> np.ndarray:
    """Depth, float32 metres from the lens's first vertex, of a planar Z pass
    ``z`` (scene units from the pinhole at the entrance pupil, which is
    ``entrance_pupil_mm`` behind the first vertex).

    A Z at or beyond ``background_z`` (Blender's background, 1e10) is inf.
    An invalid Z (NaN, 0, negative) stays invalid: it is scaled but not moved
    by the pupil, which could otherwise turn it into a positive distance. A
    valid Z nearer than the first vertex gives a depth <= 0 (invalid)."""
    z = np.asarray(z, np.float64)
    scaled = z * metres_per_unit
    d = np.where(z > 0, scaled - entrance_pupil_mm / 1000.0, scaled)
    return np.where(z >= background_z, np.inf, d).astype(np.float32)


def planar_depth_m(point_camera_space_z: float, entrance_pupil_mm: float, metres_per_unit: float = 1.0) -> float:
    """Depth in metres from the lens's first vertex of a point whose
    camera-space z (scene units) is given: a Blender camera looks down its
    -Z axis from the entrance pupil, so a point in front has z < 0. A point
    behind the first vertex gives a depth <= 0."""
    return -float(point_camera_space_z) * metres_per_unit - entrance_pupil_mm / 1000.0
