"""First-order optics checked against real rays and published figures."""
import math

import numpy as np
import pytest
from conftest import PAPER_LENSES

from dcdi_core.optics.aiming import aim_chief, launch, pupil_rays, sources, stop_grid
from dcdi_core.optics.analysis import spot_diagram
from dcdi_core.optics.lens import load_lens
from dcdi_core.optics.paraxial import first_order, image_distance_mm
from dcdi_core.optics.trace import trace


@pytest.mark.parametrize("lens_id,stated", [("mos-s1", 20.0), ("mos-s2", 24.7)])
def test_efl_within_half_percent_of_paper(lens_id, stated):
    fo = first_order(load_lens(lens_id))
    assert abs(fo.effective_focal_length_mm / stated - 1.0) < 0.005


def _axis_crossing(lens, h, depth_mm=math.inf):
    """z where a real ray from an axial object at height h in the stop crosses the axis."""
    a = aim_chief(lens, np.array([depth_mm]), np.array([0.0]))
    o, d, st, _ = pupil_rays(lens, a, np.array([[0.0, h]]))
    b = trace(lens, o, d, lens.wavelength_nm, apertures=False, status=st)
    (_, y, z), (_, dy, dz) = b.position_mm[0, 0], b.direction[0, 0]
    return z - y * dz / dy, b.direction[0, 0]


@pytest.mark.parametrize("lens_id", PAPER_LENSES)
def test_real_rays_near_axis_converge_to_paraxial_focus(lens_id):
    lens = load_lens(lens_id)
    fo = first_order(lens)
    focus_z = lens.vertex_z_mm[-1] + fo.back_focal_length_mm
    r = lens.surfaces[lens.stop_index].semi_diameter_mm
    errs = []
    for frac in (1e-2, 1e-3):
        z, _ = _axis_crossing(lens, frac * r)
        errs.append(abs(z - focus_z))
    # spherical aberration falls as h^2: a factor ~100 per decade, and vanishes
    assert errs[1] < 1e-5 * fo.effective_focal_length_mm
    assert errs[1] < errs[0] / 30 or errs[0] < 1e-9


@pytest.mark.parametrize("lens_id", PAPER_LENSES)
def test_real_efl_from_small_ray_matches_paraxial(lens_id):
    lens = load_lens(lens_id)
    fo = first_order(lens)
    a = aim_chief(lens, np.array([math.inf]), np.array([0.0]))
    ep_h = 1e-4 * fo.entrance_pupil_diameter_mm
    # a ray parallel to the axis at height ep_h (object space): f = h / sin(u')
    o, d = launch(lens, math.inf, 0.0, 0.0, ep_h, a.z_ep)
    b = trace(lens, o, d, lens.wavelength_nm, apertures=False)
    sin_u = -b.direction[1]
    assert abs(ep_h / sin_u / fo.effective_focal_length_mm - 1.0) < 1e-6


@pytest.mark.parametrize("lens_id", PAPER_LENSES)
def test_entrance_pupil_is_where_real_chief_rays_point(lens_id):
    lens = load_lens(lens_id)
    fo = first_order(lens)
    a = aim_chief(lens, np.array([math.inf]), np.array([1e-4]))
    assert a.ok.all()
    o, d = launch(lens, a.depth_mm, a.p, 0.0, a.v_chief, a.z_ep)
    # the object-space chief ray crosses the axis at the entrance pupil
    z_cross = o[0, 2] - o[0, 1] * d[0, 2] / d[0, 1]
    assert abs(z_cross - fo.entrance_pupil_position_mm) < 1e-5 * max(1.0, abs(fo.entrance_pupil_position_mm))


@pytest.mark.parametrize("lens_id", PAPER_LENSES)
def test_finite_object_image_distance_agrees_with_real_rays(lens_id):
    lens = load_lens(lens_id)
    depth_m = 1.5
    r = lens.surfaces[lens.stop_index].semi_diameter_mm
    z, _ = _axis_crossing(lens, 1e-3 * r, depth_m * 1000.0)
    q = float(image_distance_mm(lens, depth_m))
    assert abs(z - (lens.vertex_z_mm[-1] + q)) < 1e-5 * first_order(lens).effective_focal_length_mm


def test_in_focus_distance_is_conjugate_of_sensor():
    for lens_id in PAPER_LENSES:
        lens = load_lens(lens_id)
        fo = first_order(lens)
        d = fo.in_focus_object_distance_m
        if d > 0:
            assert abs(float(image_distance_mm(lens, d)) - fo.sensor_distance_mm) < 1e-9
        else:
            # a virtual object: the conjugate formula holds with the negative distance
            (a, b), (c, dd) = fo.lens_matrix
            q = -(a * d * 1000 + b) / (c * d * 1000 + dd)
            assert abs(q - fo.sensor_distance_mm) < 1e-9


@pytest.mark.parametrize("lens_id", PAPER_LENSES)
def test_on_axis_spot_is_centred_and_unvignetted(lens_id):
    lens = load_lens(lens_id)
    s = spot_diagram(lens, [0.7, math.inf], [486.13, 587.5618, 656.27], field=[0.0, 0.7], rays=32)
    c = s.centroid_mm
    assert np.abs(c[0]).max() < 1e-12                 # on axis: centred at 0
    assert np.abs(c[1, ..., 0]).max() < 1e-12          # off axis: symmetric about the meridional plane
    # the stop alone limits the axial beam at the design wavelength; at other
    # wavelengths pupil colour (stop inside the lens) moves a few edge rays out
    assert (s.vignetted_fraction[0, :, 1] == 0).all()
    assert (s.vignetted_fraction[0] < 0.02).all()


def test_stop_grid_samples_equal_area_of_the_real_stop():
    lens = load_lens("double-gauss")
    n = 128
    t = stop_grid(lens, n)
    r = lens.surfaces[lens.stop_index].semi_diameter_mm
    assert abs(len(t) / (math.pi / 4 * n * n) - 1.0) < 0.005
    assert (np.hypot(t[:, 0], t[:, 1]) <= r).all()


def test_pupil_rays_land_on_their_stop_targets_mid_lens_stop():
    lens = load_lens("double-gauss")     # stop is surface 6 of 11
    a = sources(lens, [0.7, math.inf], field=[0.0, 1.0])
    targets = stop_grid(lens, 16)
    o, d, st, resid = pupil_rays(lens, a, targets)
    b = trace(lens, o, d, lens.wavelength_nm, apertures=False, upto_surface=lens.stop_index, status=st)
    err = np.hypot(b.position_mm[..., 0] - targets[:, 0], b.position_mm[..., 1] - targets[:, 1])
    assert err.max() < 1e-6
    assert resid < 1e-6


def test_field_solve_puts_chief_ray_at_requested_height(paper_lens):
    s = spot_diagram(paper_lens, [0.7, 1e9, math.inf], [587.5618], field=[0.0, 0.5, 1.0], rays=8)
    want = np.array([0.0, 0.5, 1.0]) * paper_lens.sensor.semi_diagonal_mm
    assert np.abs(s.chief_y_mm[..., 0] - want[:, None]).max() < 1e-8


def test_depth_1e9_agrees_with_infinity(paper_lens):
    s = spot_diagram(paper_lens, [1e9, math.inf], [587.5618], field=[0.0, 1.0], rays=32)
    assert np.abs(s.rms_radius_mm[:, 0] - s.rms_radius_mm[:, 1]).max() < 1e-6
    assert np.abs(s.centroid_mm[:, 0] - s.centroid_mm[:, 1]).max() < 1e-6
