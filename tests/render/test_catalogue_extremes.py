"""Numerical stability on the catalogue's stiff cases: every lens at the
corner of its sensor (field 1), focused as close as a photographic lens of
its focal length does (8 x its focal length, about 1:7), wide open and at the
smallest stop the engine allows, and with a five-bladed iris at the corner
(the cat's eye cut by the polygon). No NaN, no negative light, every kernel
summing to one, and the renders through the lens finite and bounded."""
import math
import warnings

import numpy as np
import pytest

from dcdi_core.optics.aperture import MAX_F_NUMBER, Aperture, stopped_down, wide_open_f_number
from dcdi_core.optics.lens import available_lenses, load_lens
from dcdi_core.optics.paraxial import first_order
from dcdi_core.psf import compute
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.render.bokeh import BokehOptions, bokeh
from dcdi_core.render.distortion import chief_ray_map
from dcdi_core.render.geometry import ImageGeometry

LENSES = available_lenses()
# the closest focus, in focal lengths: a photographic lens's close limit (1:7)
CLOSEST_FOCUS_EFL = 8.0


def closest_focus_m(lens) -> float:
    return CLOSEST_FOCUS_EFL * first_order(lens).effective_focal_length_mm / 1000.0


def apertures(lens):
    n0 = wide_open_f_number(lens)
    return {"wide open": Aperture(), "smallest stop": Aperture(f_number=MAX_F_NUMBER),
            "five blades at 2x": Aperture(f_number=2.0 * n0, blades=5, rotation_deg=17.0)}


def corner_psfs(lens, focus_m: float, aperture: Aperture):
    """PSFs at field 1 of the lens stopped as asked, at the focus, nearer and at infinity."""
    settings = PSFSettings(kernel_size=41, pupil_samples=24, n_wavelengths=5, focus_distance_m=focus_m,
                           pixel_pitch_mm=lens.sensor.semi_diagonal_mm / 100.0)
    stopped = stopped_down(lens, aperture)
    depths = np.array([0.8 * focus_m, focus_m, math.inf])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # clipping warnings: the near corner blurs widely
        return [compute.psf(stopped, depth_m=float(d), field=1.0, settings=settings) for d in depths]


@pytest.mark.parametrize("lens_id", LENSES)
def test_corner_psfs_at_the_closest_focus_and_the_extreme_stops(lens_id):
    lens = load_lens(lens_id)
    focus = closest_focus_m(lens)
    got = {}
    for name, aperture in apertures(lens).items():
        for b in corner_psfs(lens, focus, aperture):
            k = b.psf
            assert np.isfinite(k).all() and (k >= 0).all(), (lens_id, name)
            assert np.isfinite(b.rms_radius_mm).all() and np.isfinite(b.relative_illumination).all(), name
            if not b.zero_energy:
                assert np.allclose(k.sum(axis=(-1, -2)), 1.0, atol=1e-4), (lens_id, name)
                assert 0.0 <= float(b.relative_illumination) <= 2.0, (lens_id, name)
        got[name] = b
    # the polygon cuts the corner's beam: the bladed kernel is not the round one of the same stop
    round_ = corner_psfs(lens, focus, Aperture(f_number=2.0 * wide_open_f_number(lens)))[-1]
    bladed = got["five blades at 2x"]
    if not (round_.zero_energy or bladed.zero_energy):
        assert bladed.vignetted_fraction[1] != round_.vignetted_fraction[1] or \
            not np.array_equal(bladed.psf, round_.psf), lens_id


@pytest.mark.parametrize("lens_id", LENSES)
def test_chief_ray_map_at_the_closest_focus_is_monotonic_and_finite(lens_id):
    lens = load_lens(lens_id)
    focus = closest_focus_m(lens)
    m = chief_ray_map(lens, focus_m=focus, near_m=0.8 * focus)
    assert np.isfinite(m.ideal_of_real).all() and np.isfinite(m.real_of_ideal).all()
    assert (np.diff(m.ideal_of_real, axis=1) > 0).all() and (np.diff(m.real_of_ideal, axis=1) > 0).all()
    assert m.reach_real_mm >= lens.sensor.semi_diagonal_mm


@pytest.mark.parametrize("lens_id", LENSES)
def test_bokeh_through_the_lens_at_the_closest_focus_is_finite_and_bounded(lens_id):
    """A small frame of the whole sensor (depths from the closest focus to
    infinity, a light 20 x the background) through the lens with its
    distortion and breathing, wide open and with blades: finite, no light
    created."""
    lens = load_lens(lens_id)
    focus = closest_focus_m(lens)
    h, w = 36, 54
    rng = np.random.default_rng(0)
    img = rng.uniform(0.0, 1.0, (h, w, 3)).astype(np.float32)
    img[h // 2, w - 4] = 20.0                        # a light near the corner's row
    depth = np.where(np.arange(w)[None, :] < w // 2, focus, np.inf) * np.ones((h, 1))
    depth[: h // 3] = 0.9 * focus
    geo = ImageGeometry.full_sensor(lens, h, w)
    for name in ("wide open", "five blades at 2x"):
        stopped = stopped_down(lens, apertures(lens)[name])
        settings = PSFSettings(kernel_size=21, pupil_samples=16, n_wavelengths=3)
        opts = BokehOptions(focus_m=focus, geometry=geo, distortion=True, settings=settings, n_layers=4)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = bokeh(img, depth, stopped, opts).image
        # (FFT round-off beside the distortion's black corners: -2e-7 at most)
        assert np.isfinite(out).all() and out.min() >= -1e-5, (lens_id, name, float(out.min()))
        assert out.max() <= 20.0 * 1.0001, (lens_id, name, float(out.max()))
        # nearly all the light arrives somewhere (the frame's border loses a little)
        assert 0.5 < out.sum() / img.sum() < 1.05, (lens_id, name, float(out.sum() / img.sum()))
