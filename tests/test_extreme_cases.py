"""Stiff and extreme cases: no NaN or inf anywhere, and the masks say why rays died."""
import math

import numpy as np
import pytest
from conftest import singlet_dict

from dcdi_core.optics import surfaces as S
from dcdi_core.optics.analysis import spot_diagram
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.errors import LensFileError
from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.optics.trace import trace

WL = 587.5618


def _finite(b):
    return np.isfinite(b.position_mm).all() and np.isfinite(b.direction).all()


def test_sweep_paper_lenses_depths_fields():
    depths = [0.7, 1e9, math.inf]
    fields = [0.0, 1.0, 1.2]
    for lens_id in ("mos-s1", "mos-s2", "double-gauss", "6p"):
        lens = load_lens(lens_id)
        for dtype in (np.float64, np.float32):
            s = spot_diagram(lens, depths, [450.0, 587.56, 650.0], field=fields, rays=24, dtype=dtype)
            b = s.bundle
            assert _finite(b), lens_id
            assert np.isfinite(s.rms_radius_mm).all() and np.isfinite(s.centroid_mm).all()
            assert np.isfinite(s.chief_y_mm).all()
            # every dead ray has a reason and the surface it died at
            dead = ~b.valid
            assert (b.failed_surface[dead] >= 0).all()
            assert (b.failed_surface[~dead] == -1).all()
            assert set(np.unique(b.status)).issubset(set(S.STATUS_NAMES))


def test_f1_double_gauss_full_field_has_no_nan():
    lens = load_lens("double-gauss")
    s = spot_diagram(lens, [0.7, math.inf], [400.0, 700.0], field=[1.0], rays=64)
    assert _finite(s.bundle)
    assert (s.vignetted_fraction < 0.5).all()
    assert np.isfinite(s.rms_radius_mm).all()


def test_radius_close_to_semi_diameter():
    # a near-hemisphere: R = 5.001, sd = 5: rays at the rim meet the surface almost tangentially
    lens = Lens.from_dict(singlet_dict(r1=5.001, sd=5.0, t=6.0, back=5.0))
    y = np.linspace(-4.9, 4.9, 201)
    o = np.stack([np.zeros_like(y), y, -np.ones_like(y)], -1)
    b = trace(lens, o, np.array([0.0, 0.0, 1.0]), WL)
    assert _finite(b)
    # the steep rim bends rays past the critical angle at the back plane, or sends them out
    assert set(np.unique(b.status)).issubset({S.OK, S.VIGNETTED, S.TIR, S.BACKWARD})
    assert (b.status == S.OK).any()


def test_semi_diameter_beyond_the_sphere_is_a_file_error():
    with pytest.raises(LensFileError, match=r"surface 2.*semi_diameter_mm"):
        Lens.from_dict(singlet_dict(r1=4.0, sd=5.0))


def test_grazing_incidence_on_a_plane():
    lens = Lens.from_dict(singlet_dict(r1=math.inf, sd=1e6))
    ang = np.radians([89.0, 89.999, 89.9999999, 90.0])
    d = np.stack([np.zeros_like(ang), np.sin(ang), np.cos(ang)], -1)
    b = trace(lens, np.array([0.0, 0.0, -1.0]), d, WL, apertures=False)
    assert _finite(b)
    assert b.status[-1] == S.BACKWARD            # parallel to the surface: never reaches it
    assert b.status[0] == S.OK                   # 89 degrees still refracts into the glass


def test_total_internal_reflection_inside_glass_is_flagged():
    # plane front, steep convex back (R = -6): a ray parallel to the axis at
    # height 5 meets the back at sin i = 5/6 > 1/1.5, beyond the critical angle
    lens = Lens.from_dict(singlet_dict(r1=math.inf, r2=-6.0, sd=5.5, t=4.0, back=10.0, nd=1.5))
    y = np.array([1.0, 5.0])
    o = np.stack([np.zeros(2), y, -np.ones(2)], -1)
    b = trace(lens, o, np.array([0.0, 0.0, 1.0]), WL, apertures=False)
    assert _finite(b)
    assert b.status[1] == S.TIR and b.failed_surface[1] == 2
    assert b.status[0] == S.OK


def test_rays_outside_every_aperture():
    lens = load_lens("mos-s1")
    o = np.array([[0.0, 50.0, -5.0], [40.0, 0.0, -5.0]])
    b = trace(lens, o, np.array([0.0, 0.0, 1.0]), WL)
    assert (b.status == S.VIGNETTED).all() and (b.failed_surface == 0).all()
    assert _finite(b)


def test_missed_sphere_is_flagged():
    lens = Lens.from_dict(singlet_dict(r1=5.0, sd=4.9, t=6.0, back=5.0, stop_first=False))
    # a ray far off axis, parallel to the axis, cannot meet a sphere of radius 5
    b = trace(lens, np.array([0.0, 7.0, -1.0]), np.array([0.0, 0.0, 1.0]), WL, apertures=False)
    assert b.status == S.MISSED and b.failed_surface == 0
    assert _finite(b)


def test_field_far_beyond_the_lens_is_aim_failure_not_nan():
    lens = load_lens("mos-s1")
    s = spot_diagram(lens, [math.inf], [587.56], field=[5.0], rays=8)
    assert not s.aimed.ok.any()
    assert (s.bundle.status == S.AIM_FAILED).all()
    assert _finite(s.bundle) and (s.vignetted_fraction == 1.0).all()


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_bad_depths_are_errors(bad):
    with pytest.raises(InputRangeError, match="depth_m"):
        spot_diagram(load_lens("mos-s1"), [bad], [587.56], field=[0.0], rays=4)


def test_depth_inside_the_lens_is_an_error():
    with pytest.raises(InputRangeError, match="in front of the first surface"):
        spot_diagram(load_lens("mos-s1"), [1e-4], [587.56], field=[0.0], rays=4)
