"""Image geometry, distortion warps, sensor noise and lens perturbation."""
import json
import math

import numpy as np
import pytest

from dcdi_core.optics.analysis import distortion as relative_distortion
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.errors import OpticsError
from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.optics.paraxial import first_order
from dcdi_core.optics.perturb import perturb_lens
from dcdi_core.render.distortion import (RadialDistortion, depth_dependence_mm, distort,
                                         radial_distortion, undistort)
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.noise import add_sensor_noise


@pytest.fixture(scope="module")
def mos():
    return load_lens("mos-s1")


@pytest.fixture(scope="module")
def mos_table(mos):
    return radial_distortion(mos)


def ball_lens():
    """A glass ball with the stop at its centre: every chief ray passes through
    the centre of curvature of both surfaces undeviated, so h_real = (R + back)
    tan(angle) exactly, the paraxial law: no distortion at any field."""
    glass = {"nd": 1.5, "vd": 50.0}
    return Lens.from_dict({
        "schema_version": 1, "id": "ball", "sensor": {"semi_diagonal_mm": 5.0},
        "surface": [
            {"radius_mm": 5.0, "thickness_mm": 5.0, "material": glass, "semi_diameter_mm": 4.9},
            {"radius_mm": math.inf, "thickness_mm": 5.0, "material": glass, "semi_diameter_mm": 1.0, "stop": True},
            {"radius_mm": -5.0, "thickness_mm": 5.0, "material": "air", "semi_diameter_mm": 4.9},
        ]})


def smooth_image(h, w, c=3):
    rr, cc = np.mgrid[0:h, 0:w].astype(np.float64)
    chans = [0.5 + 0.3 * np.sin(rr / 9.0 + k) * np.cos(cc / 13.0 - k) for k in range(c)]
    return np.stack(chans, -1).astype(np.float32)


# ------------------------------------------------------------------ geometry
def test_full_sensor_geometry_spans_the_diagonal(mos):
    g = ImageGeometry.full_sensor(mos, 1280, 1920)
    assert g.pixel_pitch_mm == pytest.approx(0.0122, rel=1e-3)   # the lens's own sensor
    assert g.center_px == (639.5, 959.5)
    # outer corner of the corner pixel at field 1
    assert g.field(-0.5, -0.5) == pytest.approx(1.0, abs=1e-12)
    assert g.field(639.5, 959.5) == 0.0
    small = ImageGeometry.full_sensor(mos, 128, 192)
    assert small.field(-0.5, -0.5) == pytest.approx(1.0, abs=1e-12)


def test_geometry_azimuth_convention(mos):
    g = ImageGeometry.from_pixel_pitch(mos, 5, 5, 0.01)
    assert g.azimuth(2, 2) == 0.0                       # on the axis
    assert g.azimuth(0, 2) == pytest.approx(0.0)        # up
    assert g.azimuth(2, 0) == pytest.approx(math.pi / 2)   # left (counter-clockwise on screen)
    assert g.azimuth(4, 2) == pytest.approx(math.pi)    # down
    assert g.azimuth(2, 4) == pytest.approx(-math.pi / 2)  # right
    assert g.radius_mm(0, 2) == pytest.approx(0.02)
    r = g.radius_mm(np.arange(5)[:, None], np.arange(5)[None, :])
    assert r.shape == (5, 5)


def test_geometry_rejects_bad_input(mos):
    for args in [(0, 10), (10, -1), (2.5, 10), (True, 3)]:
        with pytest.raises(InputRangeError):
            ImageGeometry.full_sensor(mos, *args)
    for pitch in [0.0, -1.0, math.nan, math.inf]:
        with pytest.raises(InputRangeError):
            ImageGeometry.from_pixel_pitch(mos, 10, 10, pitch)
    with pytest.raises(InputRangeError):
        ImageGeometry.from_pixel_pitch(mos, 10, 10, 0.01, center_px=(math.nan, 1.0))


# ---------------------------------------------------------------- distortion
def test_mos_s1_is_barrel_and_matches_the_analysis(mos, mos_table):
    sd = mos.sensor.semi_diagonal_mm
    t = mos_table
    assert t.real_mm[0] == 0.0 and t.ideal_mm[0] == 0.0
    assert np.all(np.diff(t.real_mm) > 0) and np.all(np.diff(t.ideal_mm) > 0)
    assert t.reach_real_mm == pytest.approx(1.5 * sd, rel=1e-6)
    ideal1 = t.ideal_from_real(sd)
    d1 = sd / ideal1 - 1.0
    assert -0.18 < d1 < -0.16                           # about -17 % at field 1
    # the same number as the real-ray analysis at the field-1 angle
    from dcdi_core.optics.analysis import real_field_angle_deg
    ang = real_field_angle_deg(mos, [1.0])[0]
    assert d1 == pytest.approx(relative_distortion(mos, [ang])[0], abs=1e-5)
    # small fields: real / ideal -> 1
    h = np.array([1e-3, 1e-2]) * sd
    assert np.all(np.abs(t.real_from_ideal(h) / h - 1.0) < 1e-4)
    # round trip of the two lookups, and NaN beyond the table
    hh = np.linspace(0, sd, 50)
    np.testing.assert_allclose(t.real_from_ideal(t.ideal_from_real(hh)), hh, atol=1e-9)
    assert np.isnan(t.ideal_from_real(2.0 * sd))


def test_small_field_ratio_tends_to_one_for_every_paper_lens(paper_lens):
    t = radial_distortion(paper_lens)
    k = slice(1, 4)
    ratio = t.real_mm[k] / t.ideal_mm[k]
    assert np.all(np.abs(ratio - 1.0) < 1e-3)
    # first samples are tiny fields: extrapolate the ratio to 0 (it goes as h^2)
    assert abs(t.real_mm[1] / t.ideal_mm[1] - 1.0) < 1e-5


def test_lens_without_distortion_gives_the_identity_warp():
    lens = ball_lens()
    t = radial_distortion(lens)
    np.testing.assert_allclose(t.real_mm[1:] / t.ideal_mm[1:], 1.0, atol=1e-9)
    g = ImageGeometry.full_sensor(lens, 33, 47)
    img = smooth_image(33, 47)
    out, valid = distort(img, lens, g, distortion=t, return_mask=True)
    assert valid.all()
    np.testing.assert_allclose(out, img, atol=1e-5)


def test_distort_moves_corner_content_inward(mos, mos_table):
    h, w = 121, 181
    g = ImageGeometry.full_sensor(mos, h, w)
    img = np.zeros((h, w, 3), np.float32)
    # a small bright square towards the lower-right corner (ideal image)
    r0, c0 = 95, 150
    img[r0 - 1:r0 + 2, c0 - 1:c0 + 2] = 1.0
    out = distort(img, mos, g, distortion=mos_table)
    m = out[..., 0]
    rr, cc = np.mgrid[0:h, 0:w]
    cy, cx = (m * rr).sum() / m.sum(), (m * cc).sum() / m.sum()
    r_ideal = g.radius_mm(r0, c0)
    r_real = g.radius_mm(cy, cx)
    assert r_real < 0.95 * r_ideal                        # barrel: real < ideal
    assert r_real == pytest.approx(mos_table.real_from_ideal(r_ideal), abs=0.5 * g.pixel_pitch_mm)
    # same azimuth
    assert g.azimuth(cy, cx) == pytest.approx(g.azimuth(r0, c0), abs=0.01)


def test_distort_then_undistort_is_the_identity_within_interpolation(mos, mos_table):
    h, w = 151, 201                                       # odd sizes
    g = ImageGeometry.full_sensor(mos, h, w)
    img = smooth_image(h, w)
    out, valid = distort(img, mos, g, distortion=mos_table, return_mask=True)
    back, valid2 = undistort(out, mos, g, distortion=mos_table, return_mask=True)
    assert out.dtype == np.float32 and back.dtype == np.float32
    assert out.shape == img.shape
    # ideal pixels whose recorded source was itself valid, away from the border
    rr, cc = np.mgrid[0:h, 0:w]
    src_real = mos_table.real_from_ideal(g.radius_mm(rr, cc))
    inner = valid2 & (g.field(rr, cc) < 0.5) & (src_real < 0.5 * g.semi_diagonal_mm)
    assert inner.sum() > 0.3 * h * w
    err = np.abs(back - img)[inner]
    assert err.mean() < 0.02


def test_constant_image_stays_constant_inside_the_mask(mos, mos_table):
    g = ImageGeometry.full_sensor(mos, 64, 97)
    img = np.full((64, 97, 3), 0.37, np.float32)
    out, valid = distort(img, mos, g, distortion=mos_table, return_mask=True)
    assert 0.5 < valid.mean() < 1.0                        # barrel: black corners
    np.testing.assert_allclose(out[valid], 0.37, rtol=1e-6)
    assert np.all(out[~valid] == 0.0)
    # corners are invalid, the centre valid
    assert not valid[0, 0] and not valid[-1, -1] and valid[32, 48]


def test_distort_two_dimensional_and_float64_inputs(mos, mos_table):
    g = ImageGeometry.full_sensor(mos, 31, 45)
    img2 = smooth_image(31, 45, 1)[..., 0]
    out2 = distort(img2, mos, g, distortion=mos_table)
    assert out2.shape == (31, 45) and out2.dtype == np.float32
    out3 = distort(np.repeat(img2[..., None], 3, -1).astype(np.float64), mos, g, distortion=mos_table)
    assert out3.dtype == np.float32
    np.testing.assert_allclose(out3[..., 1], out2, atol=1e-6)
    # the table computed inside equals the one passed in
    np.testing.assert_array_equal(distort(img2, mos, g), out2)


def test_distort_with_an_overscanned_source_fills_the_frame(mos, mos_table):
    g = ImageGeometry.full_sensor(mos, 40, 60)
    # ideal render 1.5 x larger at the same pitch, axis at its centre
    src = ImageGeometry.from_pixel_pitch(mos, 60, 90, g.pixel_pitch_mm)
    img = np.full((60, 90, 3), 0.5, np.float32)
    out, valid = distort(img, mos, g, distortion=mos_table, source_geometry=src, return_mask=True)
    assert out.shape == (40, 60, 3) and valid.all()
    np.testing.assert_allclose(out, 0.5, rtol=1e-6)


def test_distort_rejects_wrong_shapes_and_out_of_reach_images(mos, mos_table):
    g = ImageGeometry.full_sensor(mos, 20, 30)
    with pytest.raises(InputRangeError):
        distort(np.zeros((21, 30, 3), np.float32), mos, g, distortion=mos_table)
    far = ImageGeometry.from_pixel_pitch(mos, 20, 30, 2.0)   # corners at field > 1.5
    with pytest.raises(InputRangeError, match="reach"):
        distort(np.zeros((20, 30, 3), np.float32), mos, far, distortion=mos_table)


def test_non_monotonic_table_is_refused():
    with pytest.raises(OpticsError, match="lens x"):
        RadialDistortion(np.array([0.0, 1.0, 2.0]), np.array([0.0, 1.0, 0.9]), "x")


def test_depth_dependence_is_nil_for_mos_s1(mos):
    # the stop is in front of the lens: the chief ray of a direction is the
    # same ray at every object depth
    d = depth_dependence_mm(mos, 0.7)
    assert np.nanmax(d) < 1e-9


# ---------------------------------------------------------------------- noise
def test_noise_is_reproducible():
    img = np.full((32, 48, 3), 0.3, np.float32)
    a = add_sensor_noise(img, seed=5)
    b = add_sensor_noise(img, seed=5)
    c = add_sensor_noise(img, seed=6)
    assert a.dtype == np.float32 and a.shape == img.shape
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


def test_noise_mean_and_variance_follow_the_model():
    fw, read = 10000.0, 3.0
    x = 0.5
    img = np.full((256, 256, 3), x, np.float32)
    out = add_sensor_noise(img, seed=1, full_well_electrons=fw, read_noise_electrons=read).astype(np.float64)
    var = (x * fw + read ** 2) / fw ** 2
    se = math.sqrt(var / out.size)
    assert abs(out.mean() - x) < 3 * se
    assert out.var() == pytest.approx(var, rel=0.05)
    # a low full well: noise dominated by shot noise, still the same law
    out = add_sensor_noise(img, seed=2, full_well_electrons=100.0, read_noise_electrons=0.0,
                           clip=False).astype(np.float64)
    assert out.var() == pytest.approx(x * 100.0 / 100.0 ** 2, rel=0.05)


def test_noise_clipping_and_input_checks():
    img = np.full((16, 16), 0.999, np.float32)
    out = add_sensor_noise(img, seed=0, full_well_electrons=100.0)
    assert out.max() <= 1.0 and out.min() >= 0.0
    bad = np.zeros((4, 4, 3), np.float32)
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputRangeError, match="image"):
        add_sensor_noise(bad, seed=0)
    with pytest.raises(InputRangeError, match="image"):
        add_sensor_noise(-np.ones((4, 4, 3), np.float32), seed=0)
    with pytest.raises(InputRangeError, match="full_well"):
        add_sensor_noise(np.zeros((4, 4)), seed=0, full_well_electrons=0.0)
    with pytest.raises(InputRangeError, match="read_noise"):
        add_sensor_noise(np.zeros((4, 4)), seed=0, read_noise_electrons=-1.0)
    with pytest.raises(InputRangeError, match="seed"):
        add_sensor_noise(np.zeros((4, 4)), seed=1.5)


# ------------------------------------------------------------------- perturb
def _values(lens):
    return [(s.radius_mm, s.thickness_mm, s.semi_diameter_mm, s.material.nd) for s in lens.surfaces]


def test_perturbation_is_reproducible_and_bounded(paper_lens):
    a, ra = perturb_lens(paper_lens, seed=11, semi_diameters=True, model_glass=True)
    b, rb = perturb_lens(paper_lens, seed=11, semi_diameters=True, model_glass=True)
    assert _values(a) == _values(b)
    assert ra == rb
    assert json.loads(json.dumps(ra)) == ra
    assert ra["seed"] == 11 and ra["fraction"] == 0.1
    for ch in ra["changes"]:
        old, new = ch["from"], ch["to"]
        if ch["field"] == "material.nd":
            old, new = old - 1.0, new - 1.0
        assert abs(new / old - 1.0) <= 0.1 + 1e-12, ch
    # plane surfaces stay plane, every finite radius changed
    for s0, s1 in zip(paper_lens.surfaces, a.surfaces):
        if math.isinf(s0.radius_mm):
            assert math.isinf(s1.radius_mm)
        else:
            assert s1.radius_mm != s0.radius_mm
        assert s1.stop == s0.stop
    # the sensor distance is perturbed too
    assert any(c["surface"] == len(paper_lens.surfaces) and c["field"] == "thickness_mm"
               for c in ra["changes"])
    first_order(a)                                          # still a lens


def test_perturbation_differs_between_seeds_and_keeps_unselected_values(mos):
    a, _ = perturb_lens(mos, seed=1)
    b, _ = perturb_lens(mos, seed=2)
    assert _values(a) != _values(b)
    # semi-diameters (the stop's too) untouched by default
    assert [s.semi_diameter_mm for s in a.surfaces] == [s.semi_diameter_mm for s in mos.surfaces]
    # the draws do not depend on what is selected
    c, _ = perturb_lens(mos, seed=1, semi_diameters=True)
    assert [s.radius_mm for s in c.surfaces] == [s.radius_mm for s in a.surfaces]
    r, rec = perturb_lens(mos, seed=1, thicknesses=False)
    assert [s.thickness_mm for s in r.surfaces] == [s.thickness_mm for s in mos.surfaces]
    assert all(ch["field"] == "radius_mm" for ch in rec["changes"])


def test_fraction_zero_is_the_identity(paper_lens):
    p, rec = perturb_lens(paper_lens, seed=3, fraction=0.0, semi_diameters=True, model_glass=True)
    assert _values(p) == _values(paper_lens)
    assert all(ch["from"] == ch["to"] for ch in rec["changes"])


def test_perturbation_input_checks(mos):
    for f in [-0.01, 0.51, math.nan]:
        with pytest.raises(InputRangeError, match="fraction"):
            perturb_lens(mos, seed=0, fraction=f)
    with pytest.raises(InputRangeError, match="seed"):
        perturb_lens(mos, seed=-1)


def test_perturbation_that_breaks_a_surface_names_it_and_the_seed():
    # a hemisphere-like surface: sd just below |R| (5 mm thick: its edge clears the plane behind); a larger
    # semi-diameter or a smaller radius no longer fits
    lens = Lens.from_dict({
        "schema_version": 1, "id": "tight", "sensor": {"semi_diagonal_mm": 2.0},
        "surface": [
            {"radius_mm": math.inf, "thickness_mm": 1.0, "material": "air", "semi_diameter_mm": 1.0, "stop": True},
            {"radius_mm": 5.0, "thickness_mm": 5.0, "material": {"nd": 1.5, "vd": 50.0}, "semi_diameter_mm": 4.99},
            {"radius_mm": math.inf, "thickness_mm": 10.0, "material": "air", "semi_diameter_mm": 5.0},
        ]})
    failures = 0
    for seed in range(20):
        try:
            perturb_lens(lens, seed=seed, semi_diameters=True)
        except OpticsError as e:
            failures += 1
            assert "surface 2" in str(e) and f"seed={seed}" in str(e)
    assert 0 < failures < 20


def test_a_refocused_perturbed_lens_keeps_the_nominal_depth_trend():
    # MOS-S2's on-axis blur shrinks with distance; a +-10 % perturbation of the thickness to the sensor
    # defocuses it (blur up to 5x the nominal, growing with distance for some draws); moved back to the
    # nominal paraxial focus, every draw keeps the trend and stays within 1.5x of the nominal blur
    from dcdi_core.optics.analysis import spot_diagram
    from dcdi_core.optics.paraxial import prescribed_focus_diopters

    lens = load_lens("mos-s2")
    depths = np.array([0.7, 2.0, 10.0])

    def rms(l):
        return spot_diagram(l, depths, [l.wavelength_nm], field=[0.0], rays=32).rms_radius_mm[0, :, 0]

    nominal = rms(lens)
    assert nominal[0] > nominal[1] > nominal[2]
    worst_unfocused, checked = 1.0, 0
    for seed in range(6):
        try:
            plain, _ = perturb_lens(lens, seed=seed, fraction=0.1)
            moved, rec = perturb_lens(lens, seed=seed, fraction=0.1, refocus=True)
        except OpticsError:
            continue
        checked += 1
        assert rec["refocused"] and rec["changes"][-1]["field"] == "thickness_mm (refocused)"
        assert prescribed_focus_diopters(moved) == pytest.approx(prescribed_focus_diopters(lens), abs=1e-9)
        r = rms(moved)
        assert r[0] > r[2] and (r / nominal).max() < 1.5, (seed, r / nominal)
        worst_unfocused = max(worst_unfocused, float((rms(plain) / nominal).max()))
    assert checked >= 4 and worst_unfocused > 2.0          # without refocusing the same draws blur far more
