"""PSFs against independent truth: ray moments, a perfect lens, the thin-lens CoC."""
import math

import numpy as np
import pytest
from conftest import PAPER_LENSES

from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf

FAST = PSFSettings(pupil_samples=48, n_wavelengths=5)


def _moments(kernel, pitch):
    """Centroid (y, x) and second central moment (mm^2, summed over both axes)."""
    k = kernel.shape[-1]
    c = (np.arange(k) - k // 2) * pitch
    w = kernel / kernel.sum()
    my, mx = (w.sum(1) * c).sum(), (w.sum(0) * c).sum()
    var = (w.sum(1) * (c - my) ** 2).sum() + (w.sum(0) * (c - mx) ** 2).sum()
    return my, mx, var


def cartesian_lens(pitch=0.002, defocus_mm=0.0):
    """A single refracting ellipsoid (k = -1/n^2, Descartes): images an axial
    point at infinity perfectly inside the glass, where the sensor sits."""
    n = 1.5
    r = 10.0
    f_in_glass = n * r / (n - 1.0)          # 30 mm: exact for the Cartesian ellipsoid
    d = {"schema_version": 1, "id": "cartesian", "wavelength_nm": 587.5618,
         "sensor": {"semi_diagonal_mm": 1.0, "pixel_pitch_mm": pitch},
         "surface": [
             {"radius_mm": math.inf, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 2.0, "stop": True},
             {"radius_mm": r, "thickness_mm": f_in_glass + defocus_mm, "material": {"nd": n, "vd": 50.0},
              "semi_diameter_mm": 3.0, "conic": -1.0 / n ** 2}]}
    return Lens.from_dict(d)


def test_perfect_lens_kernel_is_the_identity():
    # every ray meets the chief ray at the kernel centre: the sensor records
    # the sharp pixel-integrated image as it is (deposit.py derives it)
    lens = cartesian_lens()
    r = psf(lens, field=0.0, depth_m=math.inf, wavelength_nm=587.5618,
            settings=PSFSettings(kernel_size=9, pupil_samples=32, precision="float64"))
    assert r.rms_radius_mm[1] < 1e-9          # the rays really meet in a point
    expected = np.zeros((9, 9))
    expected[4, 4] = 1.0
    assert np.abs(r.psf - expected).max() < 1e-12


def test_perfect_lens_kernel_with_the_papers_deposit_is_the_gaussian_alone():
    lens = cartesian_lens()
    s = math.sqrt(2.0) / 3.0
    r = psf(lens, field=0.0, depth_m=math.inf, wavelength_nm=587.5618,
            settings=PSFSettings(kernel_size=9, pupil_samples=32, precision="float64", deposit_sigma_px=s))
    # independent: the pixel integral of a Gaussian of sigma sqrt(2)/3 px, by math.erf
    edges = np.arange(10) - 4.5
    g = np.array([0.5 * (math.erf(b / (s * math.sqrt(2))) - math.erf(a / (s * math.sqrt(2))))
                  for a, b in zip(edges[:-1], edges[1:])])
    expected = np.outer(g, g) / np.outer(g, g).sum()
    assert np.abs(r.psf[1] - expected).max() < 1e-6


@pytest.mark.parametrize("sigma_px", [0.0, math.sqrt(2.0) / 3.0])
def test_second_moment_matches_ray_rms_radius(sigma_px):
    # monochromatic, a blur of several pixels: kernel variance = ray variance
    # + pixel sampling (2/12 px^2) [+ Gaussian deposit (2 sigma^2) + its binning (2/(12 s^2) px^2)]
    lens = load_lens("mos-s1")
    st = PSFSettings(kernel_size=61, pupil_samples=128, precision="float64", deposit_sigma_px=sigma_px)
    for field, depth in [(0.0, math.inf), (0.5, 2.0)]:
        r = psf(lens, field=field, depth_m=depth, wavelength_nm=587.5618, settings=st)
        pitch = 0.0122
        _, _, var = _moments(r.psf[1].astype(np.float64), pitch)
        sig = sigma_px * pitch
        binning = 2 * pitch ** 2 / (12 * st.oversample ** 2) if sigma_px > 0 else 0.0
        expected = r.rms_radius_mm[1] ** 2 + 2 * sig ** 2 + 2 * pitch ** 2 / 12 + binning
        assert r.energy_outside.max() < 1e-4
        assert abs(var / expected - 1.0) < 0.02, (field, depth, var, expected)


def thin_lens(focus_m):
    """A thin plano-convex lens, f ~ 100 mm, F/20, stop at the lens; refocused to focus_m."""
    from dcdi_core.optics.paraxial import refocused
    d = {"schema_version": 1, "id": "thin", "wavelength_nm": 587.5618,
         "sensor": {"semi_diagonal_mm": 2.0, "pixel_pitch_mm": 0.01},
         "surface": [
             {"radius_mm": math.inf, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 2.5, "stop": True},
             {"radius_mm": 50.0, "thickness_mm": 0.2, "material": {"nd": 1.5, "vd": 60.0}, "semi_diameter_mm": 2.6},
             {"radius_mm": math.inf, "thickness_mm": 100.0, "material": "air", "semi_diameter_mm": 2.6}]}
    return refocused(Lens.from_dict(d), focus_m)


@pytest.mark.parametrize("depth", [0.5, 2.0, math.inf])
def test_defocused_ideal_lens_gives_the_thin_lens_circle_of_confusion(depth):
    focus = 1.0
    lens = thin_lens(focus)
    r = psf(lens, field=0.0, depth_m=depth, wavelength_nm=587.5618,
            settings=PSFSettings(kernel_size=101, pupil_samples=128))
    f = 100.0                                    # 50 / (1.5 - 1)
    a = 5.0                                      # aperture diameter, mm
    s1 = focus * 1000.0
    s = depth * 1000.0
    coc = a * f * abs(s - s1) / (s * (s1 - f)) if math.isfinite(s) else a * f / (s1 - f)
    # rays fill a disk of diameter coc uniformly: RMS radius coc / (2 sqrt 2)
    assert abs(r.rms_radius_mm[1] / (coc / (2 * math.sqrt(2))) - 1.0) < 0.02


def test_library_kernel_symmetries():
    from dcdi_core.psf.library import LibraryGrid, PSFLibrary
    lens = load_lens("mos-s1")
    lib = PSFLibrary(lens, FAST, LibraryGrid(n_fields=3, n_depths=2), None)
    lib.build()
    p = lib.psf.astype(np.float64)
    # the lens is symmetric about the meridional plane: every kernel mirrors in x
    assert np.abs(p - p[..., ::-1]).max() < 1e-6
    # on axis the lens is rotationally symmetric: the kernel is symmetric under transposition
    axis = p[:, 0]
    assert np.abs(axis - axis.swapaxes(-1, -2)).max() < 1e-6
    assert np.abs(axis - axis[..., ::-1, :]).max() < 1e-6


def test_all_lenses_extreme_grid_finite_nonnegative_normalised():
    for lid in PAPER_LENSES:
        from dcdi_core.optics.aiming import sources
        from dcdi_core.psf.compute import compute_sources, spectral_samples
        lens = load_lens(lid)
        st = PSFSettings(pupil_samples=32, n_wavelengths=3, pixel_pitch_mm=0.0122 if lid != "double-gauss" else 0.0005)
        aimed = sources(lens, [0.7, 1.0, 2.0, 5.0, 10.0, math.inf], field=[0.0, 0.5, 1.0])
        wl, w = spectral_samples(st, None)
        b = compute_sources(lens, aimed, st, wl, w)
        assert np.isfinite(b.psf).all() and (b.psf >= 0).all(), lid
        assert np.abs(b.psf.sum(axis=(-1, -2)) - 1.0).max() < 1e-5, lid
        assert not b.zero_energy.any()
        assert np.isfinite(b.relative_illumination).all() and (b.relative_illumination > 0).all()
        # on axis the illumination is the axial beam's transmission (1 unless pupil colour clips it)
        assert np.abs(b.relative_illumination[0] - (1.0 - b.vignetted_fraction[0, :, 1])).max() < 1e-9, lid


def test_field_beyond_image_circle_is_zero_energy_not_nan():
    r = psf(load_lens("mos-s1"), field=5.0, depth_m=2.0, settings=FAST)
    assert r.zero_energy and (r.psf == 0).all()
    assert np.isfinite(r.vignetted_fraction).all() and (r.vignetted_fraction == 1.0).all()


def test_f1_double_gauss_full_field():
    r = psf(load_lens("double-gauss"), field=1.0, depth_m=0.7, settings=FAST)
    assert np.isfinite(r.psf).all() and not r.zero_energy


def test_depth_1e6_agrees_with_infinity():
    lens = load_lens("mos-s2")
    a = psf(lens, field=0.7, depth_m=1e6, settings=FAST)
    b = psf(lens, field=0.7, depth_m=math.inf, settings=FAST)
    assert np.abs(a.psf - b.psf).max() < 1e-4


def test_channels_sum_to_one_and_monochromatic_channels_alike():
    r = psf(load_lens("6p"), field=0.3, depth_m=3.0, wavelength_nm=550.0, settings=FAST)
    assert np.allclose(r.psf.sum(axis=(-1, -2)), 1.0, atol=1e-5)
    assert (r.psf[0] == r.psf[1]).all() and (r.psf[1] == r.psf[2]).all()


def test_small_kernel_warns_with_the_size_needed():
    with pytest.warns(KernelTooSmallWarning, match=r"a kernel of \d+ x \d+"):
        r = psf(load_lens("mos-s1"), field=1.0, depth_m=0.7, settings=PSFSettings(kernel_size=5, pupil_samples=32))
    assert r.kernel_size_needed > 5 and r.energy_outside.max() > 0.01


def test_kernel_centred_on_chief_ray_not_centroid():
    # far off axis the coma tail moves the centroid; the chief ray stays at the centre pixel's origin
    lens = load_lens("mos-s1")
    r = psf(lens, field=1.0, depth_m=math.inf, wavelength_nm=587.5618, settings=PSFSettings(pupil_samples=64, kernel_size=61))
    my, _, _ = _moments(r.psf[1].astype(np.float64), 0.0122)
    offset = r.centroid_mm[1, 1] - r.chief_ray_height_mm
    assert abs(offset) > 0.005                       # a real offset, several microns
    assert abs(my - offset) < 0.1 * abs(offset) + 0.001
