"""A lens as Blender's compositor Defocus node sees it: a thin lens.

The Defocus node (Z-buffer mode) blurs each pixel with a disc whose radius
in pixels it computes from the Z input (Potmesil and Chakravarty 1981, eq. 8;
Blender 5.0's ``node_composite_defocus.cc``)::

    v(z)   = f z / (z - f)                          image distance of depth z
    C(z)   = |v(z) - v(s)| f / (N v(z))             blur diameter on the sensor
    r(z)   = min(blur_max, C(z) / 2 * W / sensor_width)      radius, pixels

with f the scene camera's focal length (``Camera.lens``), s its focus
distance (``Camera.dof.focus_distance``), N the node's ``f_stop``, W the
image width and ``sensor_width`` the camera's (``sensor_fit`` HORIZONTAL).
All lengths there are metres (Blender units, unit scale 1).

This module fills those in from a lens prescription, from the engine's
paraxial optics (``dcdi_core``); the lab's reference of the bench against the
node (``bench_defocus``), whose Blender side only copies
:meth:`NodeDefocus.blender_settings`:

- f = the lens's paraxial EFL, N = its paraxial F-number (EFL / entrance
  pupil diameter), both from ``optics.paraxial.first_order``;
- the thin lens sits at the front principal plane H, so the node's Z is the
  planar depth from H: the depth from the first vertex (docs/design.md) plus H's
  position behind that vertex (``principal_plane_mm``; ~1-4 mm for the 6P,
  against the Z pass's entrance pupil). With Z and s measured from H, v(z)
  is the thick lens's paraxial image distance from H' exactly: the node
  focuses where ``optics.paraxial.refocused`` puts the sensor;
- sensor_width = the image's width on the lens's sensor (``full_sensor``
  geometry), so W / sensor_width = 1 / pixel pitch: the node's pixels are
  the lens's.

What stays a thin-lens approximation: the blur disc's diameter takes the
pupils at the principal planes (the real cone leaves the exit pupil); the
node's disc is uniform, achromatic and the same at every field (no
aberrations), and invalid depths (NaN, 0, negative) are given the focus
distance here (left sharp, as ``bokeh`` leaves them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.paraxial import first_order
from dcdi_core.render.camera import BLENDER_BACKGROUND_Z, BLENDER_MIN_FOCAL_LENGTH_MM, BLENDER_MIN_SENSOR_MM
from dcdi_core.render.geometry import ImageGeometry

# Blender's Defocus node: blur_max's RNA maximum (pixels)
BLENDER_MAX_BLUR_PX = 10000.0


@dataclass(frozen=True)
class NodeDefocus:
    """The thin lens of ``lens`` focused at ``focus_m`` (metres from its first
    vertex) for an ``height`` x ``width`` image spanning its sensor diagonal.
    Lengths in mm unless named _m."""

    focal_length_mm: float          # paraxial EFL
    f_number: float                 # paraxial, EFL / entrance pupil diameter
    principal_plane_mm: float       # front principal plane H behind the first vertex (+ towards the sensor)
    focus_m: float                  # focus distance from the first vertex
    pixel_pitch_mm: float
    height: int
    width: int

    @classmethod
    def for_lens(cls, lens, height: int, width: int, focus_m: float) -> "NodeDefocus":
        if isinstance(focus_m, bool) or not isinstance(focus_m, (int, float)) or not (focus_m > 0) \
                or not math.isfinite(focus_m):
            raise InputRangeError("focus_m", focus_m, "a finite distance > 0 metres")
        fo = first_order(lens)
        efl = float(fo.effective_focal_length_mm)
        if not (math.isfinite(efl) and efl > 0):
            raise InputRangeError(f"{lens.path}: effective focal length (mm)", efl, "> 0 (a real image)")
        z_h = efl - float(fo.front_focal_length_mm)      # F is ffl in front of the vertex, H is EFL behind F
        if not focus_m * 1000.0 + z_h > efl:
            raise InputRangeError("focus_m", focus_m,
                                  f"> {(efl - z_h) / 1000:.4g} m (beyond the front focal point)")
        geom = ImageGeometry.full_sensor(lens, height, width)
        return cls(efl, float(fo.f_number), z_h, float(focus_m), geom.pixel_pitch_mm, geom.height, geom.width)

    @property
    def sensor_width_mm(self) -> float:
        return self.width * self.pixel_pitch_mm

    @property
    def sensor_height_mm(self) -> float:
        return self.height * self.pixel_pitch_mm

    def node_z(self, depth_m) -> np.ndarray:
        """The node's Z input (float32 metres from H) of a depth map (metres
        from the first vertex): infinity (inf or Blender's background) ->
        Blender's background 1e10; invalid (NaN, 0, negative) -> the focus
        distance (sharp)."""
        d = np.asarray(depth_m, np.float64)
        valid = d > 0                                    # False for NaN too
        far = valid & (np.isinf(d) | (d >= BLENDER_BACKGROUND_Z))
        z = np.where(valid, d, self.focus_m) + self.principal_plane_mm / 1000.0
        return np.where(far, 1e10, z).astype(np.float32)

    @property
    def focus_z_m(self) -> float:
        """The camera's focus distance: from H, metres."""
        return self.focus_m + self.principal_plane_mm / 1000.0

    def coc_radius_px(self, depth_m) -> np.ndarray:
        """The radius (pixels) Blender's node computes for these depths
        (metres from the first vertex), before its blur_max clamp."""
        f = self.focal_length_mm / 1000.0
        z = self.node_z(depth_m).astype(np.float64)
        s = self.focus_z_m
        v_s = f * s / (s - f)
        v = f * z / (z - f)
        diameter_m = np.abs((v - v_s) * (f / (self.f_number * v)))
        return diameter_m / 2.0 * (self.width / (self.sensor_width_mm / 1000.0))

    def blur_max_px(self, depth_m) -> float:
        """The smallest blur_max that clamps none of these depths' radii (>= 1:
        below 1 the node passes the image through)."""
        r = self.coc_radius_px(depth_m)
        return float(min(BLENDER_MAX_BLUR_PX, max(1.0, math.ceil(float(r.max()) * 100) / 100)))

    def blender_settings(self, depth_m) -> dict:
        """What Blender code copies, keyed by Blender's property names:
        ``camera`` (``bpy.types.Camera``: lens, sensor_width, sensor_height,
        sensor_fit, dof.focus_distance as ``dof_focus_distance``) and
        ``node`` (``CompositorNodeDefocus``: use_zbuffer, f_stop, blur_max,
        bokeh), for the depth map ``depth_m`` (metres from the first vertex)."""
        if min(self.sensor_width_mm, self.sensor_height_mm) < BLENDER_MIN_SENSOR_MM \
                or self.focal_length_mm < BLENDER_MIN_FOCAL_LENGTH_MM:
            # scaling sensor and focal length together (camera.blender_scale) keeps the
            # view but not the node's blur: refuse rather than blur by another amount
            raise InputRangeError("sensor / focal length (mm)", (self.sensor_width_mm, self.sensor_height_mm,
                                                                 self.focal_length_mm),
                                  f">= {BLENDER_MIN_SENSOR_MM} mm each (Blender's camera minimum)")
        return {"camera": {"lens": self.focal_length_mm, "sensor_width": self.sensor_width_mm,
                           "sensor_height": self.sensor_height_mm, "sensor_fit": "HORIZONTAL",
                           "dof_focus_distance": self.focus_z_m},
                "node": {"use_zbuffer": True, "f_stop": self.f_number, "blur_max": self.blur_max_px(depth_m),
                         "bokeh": "CIRCLE"},
                "resolution": [self.height, self.width]}
