"""What the add-on reads from a Blender scene, once for every caller: the
active camera, the panel's lens (its file through the session's lens
catalogue), the lens's entrance pupil, the focus and the range kept sharp.
Apply Lens Bokeh, Simulate and Focus on Click (``operators``), the panel's
sharp range (``panel``), Lens in Renders (``render_hook``) and the viewport
preview (``viewport``) all call :func:`read_scene`; what needs only the
camera or the lens (Match Camera, Lens in Renders' check, the focus plane)
calls its parts.

Units: depths and distances in metres from the lens's first vertex, the
pupil in mm behind it; the scene's lengths are scene units times its unit
scale (``metres_per_unit``).
"""
from __future__ import annotations

import math

from dataclasses import dataclass

import bpy

from dcdi_core import app

from . import logic


@dataclass(frozen=True)
class SceneReading:
    """The scene as a lens job sees it: ``camera`` (the active camera
    object), the lens and its file, its entrance pupil (mm behind its first
    vertex), the scene's metres per unit, the focus and the kept range
    (metres; None where not read), Refocus Lens, and the render's size and
    the panel's preview size and samples (the preview's shape:
    :meth:`preview_shape`)."""

    camera: object
    lens: object
    lens_path: str
    entrance_pupil_mm: float
    metres_per_unit: float
    focus_m: float | None
    keep: tuple[float, float] | None
    refocus: bool
    render_size: tuple[int, int, float, float]       # resolution x, y; pixel aspect x, y
    preview_size: int
    samples: int
    aperture_note: str = ""          # why the camera's F-Stop was not used as it stands ('': it was, or not asked)
    preview_quality: float = 30.0    # the preview's error budget (dB; psf.budget)
    render_percentage: int = 100     # the render's resolution percentage (Output > Format)
    lens_geometry: bool = False      # Lens Geometry: the depth of field moves the picture as the lens does
    pinhole_focal_length_mm: float | None = None    # the camera's, on the lens's sensor (pinhole_focal_length_mm)

    def preview_shape(self) -> tuple[int, int]:
        """(height, width) of the preview: the render's aspect, its long side the Preview Size."""
        return logic.preview_shape(*self.render_size, self.preview_size)

    def job_shape(self, render_size: bool) -> tuple[int, int]:
        """(height, width) of a job's render: the preview's, or (``render_size``)
        the scene's render resolution at its percentage."""
        if not render_size:
            return self.preview_shape()
        x, y = self.render_size[:2]
        return logic.preview_shape(*self.render_size, max(1, round(max(x, y) * self.render_percentage / 100.0)))


def read_scene(scene, *, focus: bool = True, depsgraph=None, lens_path: str | None = None) -> SceneReading:
    """The scene's camera, lens, pupil and (``focus``) its focus and kept
    range. ``depsgraph``: the focus and kept range as it evaluated them (a
    frame of an animation render), else the scene as it stands.
    ``lens_path``: this lens file, else the panel's lens. Errors name what
    to change (no camera, the lens file, no focus object)."""
    s = scene.dcdi_lens_bokeh
    cam = camera(scene)
    if lens_path is None:
        lens, lens_path = chosen_lens(s)
    else:
        lens = logic.load_lens_cached(lens_path)
    ep = logic.lens_readout(lens_path)["entrance_pupil_mm"]
    lens, note = camera_aperture(cam, s, lens)
    focus_m = keep = None
    if focus:
        focus_m, keep = focus_and_keep(scene, cam, s, ep, depsgraph)
    r = scene.render
    size = (r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y)
    return SceneReading(cam, lens, lens_path, ep, metres_per_unit(scene), focus_m, keep, bool(s.refocus),
                        size, s.preview_size, s.samples, note, float(s.preview_quality), int(r.resolution_percentage),
                        bool(s.lens_geometry), pinhole_focal_length_mm(cam, size, lens))


# ------------------------------------------------------------------ the parts
def metres_per_unit(scene) -> float:
    return float(scene.unit_settings.scale_length)


def camera(scene):
    """The scene's active camera, which must be a perspective camera."""
    cam = scene.camera
    if cam is None:
        raise logic.BokehInputError("the scene has no active camera: add one (Add > Camera) and make it the "
                                    "active camera (View > Cameras > Set Active Object as Camera)")
    if cam.type != "CAMERA":
        raise logic.BokehInputError(f"the active camera {cam.name!r} is a {cam.type.lower()}, not a camera")
    if cam.data.type != "PERSP":
        raise logic.BokehInputError(f"camera {cam.name!r} is {cam.data.type.lower()}: "
                                    "Lens Bokeh needs a perspective camera (Camera > Type > Perspective)")
    return cam


def pinhole_focal_length_mm(cam, render_size, lens) -> float:
    """The camera's focal length on the scale of the lens's sensor (mm): a
    job's image spans the lens's sensor diagonal, so it is the semi-diagonal
    over the tangent of half the render's diagonal angle of view (Blender's
    Sensor Fit: Auto fits the sensor width to the longer side). Equal to the
    lens's focal length after Match Camera to Lens at infinity; what the
    engine reads the render's scale by where the lens moves the picture."""
    d = cam.data
    rx, ry, ax, ay = render_size
    w, h = float(rx) * float(ax), float(ry) * float(ay)
    fit = d.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if w >= h else "VERTICAL"
        side = float(d.sensor_width)
    else:
        side = float(d.sensor_width if fit == "HORIZONTAL" else d.sensor_height)
    per_unit = side / float(d.lens) / (w if fit == "HORIZONTAL" else h)      # tan of the angle per pixel
    return float(lens.sensor.semi_diagonal_mm) / (per_unit * math.hypot(w, h) / 2.0)


def camera_aperture(cam, settings, lens):
    """(the lens, stopped down to the camera's F-Stop and shaped by its Blades
    and Rotation when Camera Aperture is on; a note for the panel, or ''):
    ``logic.camera_aperture`` on the camera's Depth of Field settings. The
    entrance pupil's position does not move with the stop (paraxially)."""
    if not settings.use_camera_aperture:
        return lens, ""
    dof = cam.data.dof
    return logic.camera_aperture(lens, float(dof.aperture_fstop), int(dof.aperture_blades),
                                 float(dof.aperture_rotation))


def user_lens_dir(create: bool = False) -> str:
    """Folder of lenses imported from Zemax files: the extension's user folder
    (Blender 4.2+), else a folder in the user's scripts."""
    pkg = __package__ or "blender_addon"
    if hasattr(bpy.utils, "extension_path_user") and pkg.startswith("bl_ext."):
        return bpy.utils.extension_path_user(pkg, path="lenses", create=create)
    return bpy.utils.user_resource("SCRIPTS", path="dcdi_lenses", create=create)


def catalogue():
    """The lenses the panel offers (``logic.lens_catalogue``: the lens folders and the imported lenses)."""
    return logic.lens_catalogue([user_lens_dir()])


def lens_file(lens_id: str) -> str | None:
    """Path of the lens ``lens_id``'s TOML file (None when there is none)."""
    return logic.lens_file(lens_id, [user_lens_dir()])


def chosen_lens(settings):
    """(lens, path) of the panel's lens; errors name the file and the field."""
    path = lens_file(settings.lens)
    if path is None:
        raise logic.BokehInputError(f"no lens file for {settings.lens!r}: pick a lens in the panel "
                                    "(lenses/*.toml or Import Zemax File)")
    try:
        return logic.load_lens_cached(path), path
    except app.errors.DcdiError as e:
        raise logic.BokehInputError(f"the lens file is broken: {logic.message(e)}") from None


def focus_metres(scene, cam, settings, entrance_pupil_mm: float, depsgraph=None) -> float:
    """Focus distance in metres from the lens's first vertex: the panel's
    distance, its focus object's origin, or the camera's own depth-of-field
    focus (its focus object, else its focus distance). The panel's distance
    and the camera's are measured as Blender's depth of field measures them:
    from the camera (the entrance pupil) along its view axis. ``depsgraph``:
    read the values it evaluated (a frame of an animation render), else the
    scene as it stands."""
    if depsgraph is not None:
        settings = scene.evaluated_get(depsgraph).dcdi_lens_bokeh
        cam = cam.evaluated_get(depsgraph)
    mpu = metres_per_unit(scene)
    if settings.focus_mode == "DISTANCE":        # from the camera, as the camera's own distance below
        return app.camera.planar_depth_m(-settings.focus_distance, entrance_pupil_mm, mpu)
    if settings.focus_mode == "CAMERA":
        dof = cam.data.dof
        obj = dof.focus_object
        if obj is None:            # the camera's distance runs from the camera, i.e. the entrance pupil
            return app.camera.planar_depth_m(-dof.focus_distance, entrance_pupil_mm, mpu)
    else:
        obj = settings.focus_object
        if obj is None:
            raise logic.BokehInputError("focus is set to Object but no focus object is chosen")
    if depsgraph is not None:
        obj = obj.evaluated_get(depsgraph)
    return point_depth_m(scene, cam, obj.matrix_world.translation, entrance_pupil_mm)


def point_depth_m(scene, cam, point, entrance_pupil_mm: float) -> float:
    """Depth in metres from the lens's first vertex of the world ``point``
    (scene units): its depth along the camera's view axis."""
    z = (cam.matrix_world.inverted() @ point).z          # camera space: the camera looks down -Z
    return app.camera.planar_depth_m(z, entrance_pupil_mm, metres_per_unit(scene))


def focus_and_keep(scene, cam, settings, entrance_pupil_mm: float, depsgraph=None):
    """(focus, (near, far)): the focus (:func:`focus_metres`) and the range
    kept sharp around it, metres."""
    focus = focus_metres(scene, cam, settings, entrance_pupil_mm, depsgraph)
    s = scene.evaluated_get(depsgraph).dcdi_lens_bokeh if depsgraph is not None else settings
    mpu = metres_per_unit(scene)
    return focus, logic.keep_range(focus, s.keep_front * mpu, s.keep_behind * mpu)


def inputs_key(scene) -> str:
    """What a lens job's result depends on, in the panel and the camera: the
    panel's settings, the active camera's name, placement, lens and depth
    of field, the render's size. The status of the last job is shown while
    this is unchanged (the panel, ``panel.status_lines``); a change of the
    scene's objects is not in it."""
    def placed(obj):
        return None if obj is None else [obj.name, [round(v, 6) for row in obj.matrix_world for v in row]]

    s = scene.dcdi_lens_bokeh
    parts = [s.lens, s.focus_mode, round(s.focus_distance, 9), placed(s.focus_object), s.refocus, s.lens_geometry,
             round(s.keep_front, 9), round(s.keep_behind, 9), s.preview_size, round(s.preview_quality, 6), s.samples,
             s.sensor_noise,
             s.correction_method, s.correction_model, s.apply_render_size, scene.render.resolution_percentage]
    cam = scene.camera
    parts.append(placed(cam))
    if cam is not None and cam.type == "CAMERA":
        d = cam.data
        parts += [d.type, round(d.lens, 6), round(d.sensor_width, 6), round(d.sensor_height, 6), d.sensor_fit,
                  placed(d.dof.focus_object), round(d.dof.focus_distance, 9)]
        if s.use_camera_aperture:
            parts += [round(d.dof.aperture_fstop, 6), d.dof.aperture_blades, round(d.dof.aperture_rotation, 6)]
    r = scene.render
    parts += [r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y, scene.unit_settings.scale_length]
    return repr(parts)
