"""The pinhole camera that frames like a lens, and planar depth (docs/design.md).

A renderer such as Blender draws an all-in-focus image through a pinhole;
the lens's blur and distortion are added afterwards from its PSFs. For the
two to line up the pinhole must see what the lens sees:

- it sits at the lens's entrance pupil (the centre of projection of the
  object-space chief rays), ``entrance_pupil_mm`` behind the first vertex;
- its focal length is the scale of the lens's ideal image
  (:func:`ideal_scale_mm`: the paraxial image height per unit tan of the
  field angle at the sensor where the prescription puts it): the EFL for a
  lens focused at infinity; 18.94 mm for MOS-S1, whose sensor sits 4
  diopters inside its infinity focus, against its 19.95 mm EFL. With a
  focus distance, the one that frames what the lens focused there shows
  (:func:`framing_focal_length_mm`: breathing and distortion);
- its sensor is the image's rectangle on the lens's sensor when the image
  spans the sensor's full diagonal (``ImageGeometry.full_sensor``), so the
  pinhole's diagonal field of view is 2 atan(semi-diagonal / focal length).

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


def ideal_scale_mm(lens) -> float:
    """The scale of the lens's ideal (pinhole) image: paraxial image height
    (mm) per unit p = tan(field angle), the prescription as it stands (its
    EFL when focused at infinity). What ``distortion`` calls the ideal
    height is p times this."""
    from ..optics.paraxial import paraxial_image_height_mm
    p = 1e-3
    return float(paraxial_image_height_mm(lens, math.degrees(math.atan(p))) / p)


def framing_focal_length_mm(lens, focus_m: float, height: int, width: int, near_m: float = 0.7) -> float:
    """The focal length (mm, on the lens's sensor) of the pinhole whose
    ``height`` x ``width`` frame (spanning the sensor's diagonal) holds all
    that ``lens`` focused at ``focus_m`` metres shows on that frame, at any
    depth from ``near_m`` to infinity: the longest for which every point of
    the frame's border has its source inside the pinhole's frame (the
    corner exactly, for barrel distortion; the middle of the long side for
    pincushion). Longer than the EFL where the lens breathes in as it
    focuses close."""
    from .distortion import chief_ray_map
    m = chief_ray_map(lens, focus_m=focus_m, near_m=min(near_m, focus_m))
    g = ImageGeometry.full_sensor(lens, height, width)
    half_w, half_h = g.width * g.pixel_pitch_mm / 2.0, g.height * g.pixel_pitch_mm / 2.0
    t = np.linspace(0.0, 1.0, 257)
    # a quadrant's border (radial symmetry): the right side and the top side, corner included
    bx = np.concatenate([np.full(t.size, half_w), t * half_w])
    by = np.concatenate([t * half_h, np.full(t.size, half_h)])
    r = np.hypot(bx, by)
    ideal = m.widest_ideal_from_real(r)
    return float(ideal_scale_mm(lens) * np.min(r / ideal))


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole that frames an H x W image like the lens (lengths in mm).

    ``focal_length_mm`` is the scale of the lens's ideal image
    (:func:`ideal_scale_mm`, its EFL when focused at infinity) or its framing
    at a focus distance; ``sensor_width_mm`` x
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
    def for_lens(cls, lens, height: int, width: int, *, focus_m: float | None = None,
                 near_m: float = 0.7) -> "PinholeCamera":
        """The pinhole of ``lens`` for an image of ``height`` x ``width`` px
        that spans the lens's sensor diagonal: its focal length the scale
        of the lens's ideal image (:func:`ideal_scale_mm`: the engine reads
        a render at it) or, with ``focus_m`` (metres), the one that frames what
        the lens focused there shows (breathing and distortion: the image's
        corner sees the direction whose chief ray lands at the sensor's
        corner, the widest over depths from ``near_m`` to infinity, so that
        the lens's frame is covered at every depth)."""
        fo = first_order(lens)
        efl = float(fo.effective_focal_length_mm)
        if not (math.isfinite(efl) and efl > 0):
            raise InputRangeError(f"{lens.path}: effective focal length (mm)", efl,
                                  "> 0 (a lens that forms a real image of distant objects)")
        geom = ImageGeometry.full_sensor(lens, height, width)
        f = ideal_scale_mm(lens) if focus_m is None else framing_focal_length_mm(lens, focus_m, height, width, near_m)
        return cls(f, geom.width * geom.pixel_pitch_mm, geom.height * geom.pixel_pitch_mm,
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
