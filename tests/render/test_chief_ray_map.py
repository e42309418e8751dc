"""The chief-ray map: where a lens, focused as it is, puts each object
direction at each depth (focus breathing, depth-dependent distortion),
against chief rays found independently by tracing fans of rays
(``lab.breathing.traced_chief_height``: no aiming)."""
import math

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.optics.paraxial import paraxial_image_height_mm, refocused
from dcdi_core.render.base import on_sensor
from dcdi_core.render.distortion import chief_ray_map, radial_distortion
from dcdi_core.render.geometry import ImageGeometry
from lab.breathing import traced_chief_height

SONNAR = "zeiss-sonnar-50mm-f1-5"
# the tolerance of the map against traced chief rays: 0.05 px of a 5 um pixel
TOL_MM = 0.05 * 0.005


def ideal_per_p(lens) -> float:
    """The pinhole's scale (mm of ideal height per unit p) of the prescription."""
    return float(paraxial_image_height_mm(lens, math.degrees(math.atan(1e-3))) / 1e-3)


@pytest.mark.parametrize("lens_id, focus_m", [(SONNAR, 2.3), (SONNAR, None), ("nikkor-24mm-f2", 0.9),
                                              ("6p", 3.1), ("nikkor-85mm-f1-4", 1.1)])
def test_map_equals_traced_chief_rays_at_held_out_depths_and_focus(lens_id, focus_m):
    lens = load_lens(lens_id)
    m = chief_ray_map(lens, focus_m=focus_m, near_m=0.7)
    focused = lens if focus_m is None else refocused(lens, focus_m)
    sd, c = lens.sensor.semi_diagonal_mm, ideal_per_p(lens)
    # depths and fields between the map's samples (9 depths uniform in diopters)
    for depth_m, field in [(0.83, 0.95), (2.9, 0.61), (17.0, 0.33), (1.21, 0.99), (math.inf, 0.8)]:
        ideal = field * sd
        diopters = 0.0 if math.isinf(depth_m) else 1.0 / depth_m
        want = traced_chief_height(focused, depth_m * 1000.0, ideal / c)
        got = float(m.real_from_ideal(ideal, diopters))
        assert abs(got - want) < TOL_MM, (lens_id, focus_m, depth_m, field, got - want)
        back = float(m.ideal_from_real(want, diopters))
        assert abs(back - ideal) < TOL_MM * 2, (lens_id, depth_m, field, back - ideal)


@pytest.mark.parametrize("lens_id, breathing", [(SONNAR, (0.04, 0.07)), ("nikkor-85mm-f1-4", (0.05, 0.09))])
def test_refocusing_breathes_as_the_traced_chief_rays_say(lens_id, breathing):
    """From infinity to 1.5 m the corner of a fast short tele moves out by
    several percent; the map says by how much to a tenth of a 100 um pixel."""
    lens = load_lens(lens_id)
    sd, c = lens.sensor.semi_diagonal_mm, ideal_per_p(lens)
    at_inf = chief_ray_map(lens, focus_m=math.inf, near_m=0.7)
    at_close = chief_ray_map(lens, focus_m=1.5, near_m=0.7)
    p = 0.95 * sd / c
    traced_inf = traced_chief_height(refocused(lens, math.inf), math.inf, p)
    traced_close = traced_chief_height(refocused(lens, 1.5), 1500.0, p)
    got = float(at_close.real_from_ideal(p * c, 1 / 1.5) - at_inf.real_from_ideal(p * c, 0.0))
    assert abs(got - (traced_close - traced_inf)) < 0.1 * 0.1      # 0.1 px of 100 um
    lo, hi = breathing
    assert lo < got / traced_inf < hi, got / traced_inf


def test_depth_dependence_is_the_pupil_aberration():
    """At one focus, the Sonnar's corner moves with the object's depth (its
    entrance pupil 33 mm inside the lens), MOS-S1's does not (stop in front)."""
    sonnar = chief_ray_map(load_lens(SONNAR), focus_m=1.5, near_m=0.7)
    sd = load_lens(SONNAR).sensor.semi_diagonal_mm
    moved = float(sonnar.real_from_ideal(sd, 1 / 1.5) - sonnar.real_from_ideal(sd, 1 / 6.0))
    assert -0.1 < moved < -0.03, moved          # 0.3 to 1 px of 100 um, toward the axis for the nearer object
    mos = chief_ray_map(load_lens("mos-s1"), near_m=0.3)
    sd = load_lens("mos-s1").sensor.semi_diagonal_mm
    assert abs(float(mos.real_from_ideal(sd, 1 / 0.3) - mos.real_from_ideal(sd, 0.0))) < 1e-9


def test_prescribed_focus_at_infinity_is_the_old_table():
    lens = load_lens("mos-s2")
    m = chief_ray_map(lens, near_m=0.7)
    t = radial_distortion(lens)
    h = np.linspace(0.0, lens.sensor.semi_diagonal_mm, 50)
    assert np.max(np.abs(m.real_from_ideal(h, 0.0) - t.real_from_ideal(h))) < 1e-5


def test_on_sensor_moves_each_point_by_the_chief_ray_of_its_own_depth():
    """A bright point near the corner of a pinhole render lands on the sensor
    where the traced chief ray of its depth says, refocused; a far one beside
    it lands where its own depth says (a crop at 20 um, field 0.75 to 0.95)."""
    lens = load_lens(SONNAR)
    geo = ImageGeometry.from_pixel_pitch(lens, 101, 201, 0.02, center_px=(50.0, -800.0))
    c = ideal_per_p(lens)
    img = np.zeros((101, 201, 3), np.float32)
    depth = np.full((101, 201), 1.5)
    cols = {1.5: 40, 6.0: 100}
    for d, col in cols.items():
        img[50, col] = 1.0
        depth[46:55, col - 4:col + 5] = d
    m = chief_ray_map(lens, focus_m=1.5, near_m=0.7)
    out, dep, valid = on_sensor(img, depth, lens, geo, distortion=m, interpolation="linear")
    old, _, _ = on_sensor(img, depth, lens, geo, distortion=radial_distortion(lens), interpolation="linear")
    focused = refocused(lens, 1.5)
    for d, col in cols.items():
        ideal = (col - geo.center_px[1]) * geo.pixel_pitch_mm
        want_px = geo.center_px[1] + traced_chief_height(focused, d * 1000.0, ideal / c) / geo.pixel_pitch_mm
        near = np.arange(int(want_px) - 3, int(want_px) + 5)
        row = out[50, near, 0]
        centroid = float((row * near).sum() / row.sum())
        assert abs(centroid - want_px) < 0.1, (d, centroid, want_px)
        assert float(dep[50, int(round(want_px))]) == d
        # the old table (infinity, the prescribed sensor) puts it 40 px short
        assert old[50, near, 0].sum() < 1e-6


def test_chief_ray_map_refuses_bad_arguments():
    lens = load_lens("6p")
    for kw in [dict(near_m=0.0), dict(near_m=float("nan")), dict(focus_m=-1.0), dict(n_depths=1),
               dict(max_field=0.0), dict(n=True)]:
        with pytest.raises(InputRangeError):
            chief_ray_map(lens, **kw)


def test_a_camera_framed_at_the_focus_keeps_the_lens_framing():
    """Match Camera's pinhole (framing the lens focused at 1.5 m): the
    sensor's frame shows all of the pinhole render, to its edge, at the
    widest depth; a render at the lens's own focal length would leave its
    border 5 % further out."""
    from dcdi_core.render.camera import PinholeCamera, ideal_scale_mm
    from dcdi_core.render.distortion import _source_positions
    from dcdi_core.render.request import RenderRequest
    from dcdi_core.render.base import sensor_mapping

    lens = load_lens(SONNAR)
    cam = PinholeCamera.for_lens(lens, 200, 300, focus_m=1.5)
    assert 1.05 < cam.focal_length_mm / ideal_scale_mm(lens) < 1.09
    sensor, source = RenderRequest(lens, pinhole_focal_length_mm=cam.focal_length_mm).geometries(200, 300)
    assert source is not None and source.pixel_pitch_mm < sensor.pixel_pitch_mm
    m = chief_ray_map(lens, focus_m=1.5, near_m=0.7)
    radius, reach, _ = sensor_mapping(m)
    y, x, valid = _source_positions(sensor, source, radius, reach)
    # every pixel's source inside the render, and the frame's border reaching its edge (the Sonnar's
    # moustache distortion binds at the long side, not at the corner)
    assert valid.all()
    margins = [y[0].min(), x[:, 0].min(), 199 - y[-1].max(), 299 - x[:, -1].max()]
    assert -0.5 <= min(margins) < 0.6, margins
    # the lens's own focal length (no pinhole given): the corner reaches 5 % beyond the middle's pixels
    sensor, source = RenderRequest(lens).geometries(200, 300)
    y, x, _ = _source_positions(sensor, sensor, radius, reach)
    assert float(x[0, 0]) > 5.0
    # a pinhole focal length is checked when the request is made
    for bad in (0.0, -3.0, float("nan"), True):
        with pytest.raises(InputRangeError):
            RenderRequest(lens, pinhole_focal_length_mm=bad)

