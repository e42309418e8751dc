"""The pinhole camera of a lens (dcdi_core.render.camera): focal length, field
of view, Blender's 1 mm sensor minimum, planar depth; and (pip bpy) the
factory's Blender camera frames like the lens."""
import math

import numpy as np
import pytest

from conftest import singlet_dict
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.optics.paraxial import first_order, prescribed_focus_diopters
from dcdi_core.render.camera import (BLENDER_MIN_SENSOR_MM, PinholeCamera, depth_from_planar_z, ideal_scale_mm,
                                     planar_depth_m)

H, W = 480, 640


def true_fov_deg(lens) -> float:
    """The lens's paraxial diagonal field of view on its sensor where the
    prescription puts it: 2 atan(semi-diagonal / its ideal image's scale)."""
    return math.degrees(2.0 * math.atan(lens.sensor.semi_diagonal_mm / ideal_scale_mm(lens)))


def blender_fov_deg(settings: dict, height: int, width: int, clamp_mm: float = BLENDER_MIN_SENSOR_MM) -> float:
    """The diagonal field of view Blender renders with these settings: it clamps
    each length to ``clamp_mm``; with horizontal fit the sensor width spans the
    image width, so the image diagonal on the sensor is width * hypot(H, W) / W."""
    assert settings["sensor_fit"] == "HORIZONTAL"
    sensor_w, f = max(settings["sensor_width"], clamp_mm), max(settings["lens"], clamp_mm)
    diagonal = sensor_w * math.hypot(height, width) / width
    return math.degrees(2.0 * math.atan(diagonal / (2.0 * f)))


def test_pinhole_has_the_paraxial_focal_length_and_spans_the_sensor_diagonal(paper_lens):
    cam = PinholeCamera.for_lens(paper_lens, H, W)
    assert cam.focal_length_mm == ideal_scale_mm(paper_lens)
    stated = paper_lens.stated["effective_focal_length_mm"]
    if abs(prescribed_focus_diopters(paper_lens)) < 0.5:
        # focused near infinity: the focal length the paper's tables state (lenses/*.toml [stated]), not
        # the code's own paraxial trace
        assert cam.focal_length_mm == pytest.approx(stated, rel=3e-3)
    else:
        # MOS-S1 and MOS-S2: the sensor 4 diopters inside the infinity focus, the image 5 % smaller than
        # the EFL's (a paraxial trace to that sensor, independent of ideal_scale_mm)
        fo = first_order(paper_lens)
        (a, b), (c, d) = fo.lens_matrix
        u0 = 1e-4
        y0 = -fo.entrance_pupil_position_mm * u0
        traced = (a * y0 + b * u0 + fo.sensor_distance_mm * (c * y0 + d * u0)) / u0
        assert cam.focal_length_mm == pytest.approx(traced, rel=1e-9)
        assert cam.focal_length_mm < 0.97 * stated
    assert math.hypot(cam.sensor_width_mm, cam.sensor_height_mm) == pytest.approx(
        2.0 * paper_lens.sensor.semi_diagonal_mm, rel=1e-12)
    assert cam.sensor_width_mm / cam.sensor_height_mm == pytest.approx(W / H, rel=1e-12)
    assert cam.diagonal_field_of_view_deg == pytest.approx(true_fov_deg(paper_lens), rel=1e-9)
    assert (cam.height, cam.width) == (H, W)


def test_blender_settings_keep_the_lens_field_of_view_within_blenders_limits(paper_lens):
    s = PinholeCamera.for_lens(paper_lens, H, W).blender_camera_settings()
    assert min(s["sensor_width"], s["sensor_height"], s["lens"]) >= BLENDER_MIN_SENSOR_MM * (1 - 1e-12)
    assert blender_fov_deg(s, H, W) == pytest.approx(true_fov_deg(paper_lens), rel=1e-3)


def test_double_gauss_sensor_is_scaled_with_the_focal_length_not_clamped():
    lens = load_lens("double-gauss")
    cam = PinholeCamera.for_lens(lens, H, W)
    assert cam.sensor_width_mm < BLENDER_MIN_SENSOR_MM              # the case Blender would clamp
    scale = cam.blender_scale()
    s = cam.blender_camera_settings()
    assert scale > 1 and s["sensor_height"] == pytest.approx(BLENDER_MIN_SENSOR_MM)
    assert s["lens"] == pytest.approx(scale * cam.focal_length_mm) and s["sensor_width"] == pytest.approx(
        scale * cam.sensor_width_mm)
    fov = true_fov_deg(lens)
    assert blender_fov_deg(s, H, W) == pytest.approx(fov, rel=1e-3)
    # the unscaled camera, clamped by Blender, sees about 3.5 times wider
    unscaled = cam.blender_camera_settings(min_sensor_mm=0.0, min_focal_length_mm=0.0)
    assert blender_fov_deg(unscaled, H, W) > 3.0 * fov


def test_lens_without_a_real_focal_length_is_refused():
    diverging = Lens.from_dict(singlet_dict(r1=-50.0))
    assert first_order(diverging).effective_focal_length_mm < 0
    with pytest.raises(InputRangeError, match="effective focal length"):
        PinholeCamera.for_lens(diverging, H, W)


@pytest.mark.parametrize("metres_per_unit", [1.0, 0.01])
def test_planar_depth_round_trips_between_pupil_and_first_vertex(metres_per_unit):
    ep_mm = first_order(load_lens("6p")).entrance_pupil_position_mm      # 14.6 mm behind the first vertex
    depth_m = np.array([0.05, 0.7, 2.0, 37.5])
    # the scene Z from the pinhole (entrance pupil) of points at those depths from the first vertex
    z = (depth_m + ep_mm / 1000.0) / metres_per_unit
    assert depth_from_planar_z(z, ep_mm, metres_per_unit) == pytest.approx(depth_m, rel=1e-6)
    # a focus object on the axis, in camera space (the camera looks down -Z)
    assert [planar_depth_m(-v, ep_mm, metres_per_unit) for v in z] == pytest.approx(depth_m, rel=1e-12)
    assert depth_from_planar_z(z, ep_mm, metres_per_unit).dtype == np.float32


def test_background_is_infinity_and_invalid_z_stays_invalid():
    d = depth_from_planar_z(np.array([1e10, 1e9, 3e38, np.inf]), 14.6)
    assert np.isinf(d).all() and (d > 0).all()
    assert np.isfinite(depth_from_planar_z(np.array([9.9e8]), 14.6)).all()
    bad = depth_from_planar_z(np.array([np.nan, 0.0, -1.0]), 14.6)
    assert np.isnan(bad[0]) and (bad[1:] <= 0).all()
    # a pupil in front of the first vertex must not turn an invalid Z into a distance
    assert not (depth_from_planar_z(np.array([0.0, -0.001]), -5.0) > 0).any()
    # a point between the pupil and the first vertex is not a valid depth either
    assert depth_from_planar_z(np.array([0.01]), 14.6)[0] <= 0
    assert planar_depth_m(+1.0, 0.0) < 0                                  # behind the camera


def test_factory_camera_frames_like_the_double_gauss():
    bpy = pytest.importorskip("bpy")
    from blender_addon.factory.render import RenderSettings, setup_render

    lens = load_lens("double-gauss")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    pinhole = setup_render(scene, lens, 24, 32, RenderSettings(), seed=0)
    cam = scene.camera.data
    assert cam.sensor_fit == "HORIZONTAL" and pinhole.blender_scale() > 1
    # Blender's own angle (horizontal: the sensor width) against the lens's
    h_fov = 2.0 * math.atan(pinhole.sensor_width_mm / (2.0 * pinhole.focal_length_mm))
    assert cam.angle == pytest.approx(h_fov, rel=1e-3)
    diagonal = cam.sensor_width * math.hypot(24, 32) / 32
    assert math.degrees(2.0 * math.atan(diagonal / (2.0 * cam.lens))) == pytest.approx(true_fov_deg(lens), rel=1e-3)
    assert scene.camera.matrix_world.translation.length == 0.0      # the pinhole (pupil) at the scene origin
