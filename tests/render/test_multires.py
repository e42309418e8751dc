"""Multi-resolution bokeh (render/multires.py) against the exact layered and plain paths."""

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render import multires as mr
from lab.simulation_accuracy import psnr
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.bokeh import BokehOptions, bokeh

H, W = 96, 128
pytestmark = pytest.mark.filterwarnings("ignore::dcdi_core.psf.compute.KernelTooSmallWarning")


@pytest.fixture(scope="module")
def case():
    """6P at its full-resolution pitch (a 1280 x 1920 image on its sensor): a
    96 x 128 crop off axis, where the defocus kernels are 10-15 px wide."""
    lens = load_lens("6p")
    full = ImageGeometry.full_sensor(lens, 1280, 1920)
    geom = ImageGeometry.from_pixel_pitch(lens, H, W, full.pixel_pitch_mm, center_px=(300.0, 400.0))
    lib = PSFLibrary(lens, PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=31, band_nm=(400.0, 700.0),
                                       pixel_pitch_mm=full.pixel_pitch_mm), LibraryGrid(n_fields=8, n_depths=4), None)
    rng = np.random.default_rng(3)
    # a band-limited-ish texture (blocks of 4 px) with a few bright points, as bokeh scenes have
    img = np.repeat(np.repeat(rng.random((H // 4, W // 4, 3)), 4, 0), 4, 1).astype(np.float32)
    img[rng.integers(0, H, 6), rng.integers(0, W, 6)] = 4.0
    depth = np.full((H, W), 8.0)
    depth[:, 100:] = 0.5
    depth[30:66, 12:60] = 1.2                                   # the kept subject
    return lens, geom, lib, img, depth


def test_level_rule_keeps_narrow_kernels_at_full_resolution():
    assert mr.level_for([0.0, 3.9, 4.0, 7.9, 8.0, 100.0], 4.0, 2).tolist() == [0, 0, 0, 0, 1, 2]
    assert mr.level_for([100.0], None, 3).tolist() == [0]
    assert mr.level_for([100.0], 4.0, 0).tolist() == [0]
    assert mr.level_for([31.9, 32.0], 4.0, 3).tolist() == [2, 3]
    with pytest.raises(InputRangeError):
        mr.check_multires(0.0, 2, 16)
    with pytest.raises(InputRangeError):
        mr.check_multires(4.0, 5, 16)
    with pytest.raises(InputRangeError):
        mr.check_multires(4.0, 2, 7)


def test_narrow_kernels_give_the_exact_path(case):
    lens, geom, lib, img, depth = case
    ex = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, convolution="windows", interp_eps=None,
                                              seam_tol=None), library=lib)
    mres = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, multires=1000.0), library=lib)
    assert all(sum(lv[1:]) == 0 for lv in mres.info["layer_levels"])
    # equal to float32 rounding: the exact path skips the patches beyond every
    # kernel's reach of a layer and sizes its kernels to their support
    assert np.abs(ex.image - mres.image).max() <= 1e-6 * max(1.0, float(np.abs(ex.image).max()))


def test_upsample_keeps_constants_and_places_samples_at_block_centres():
    c = np.full((5, 7, 2), 0.3, np.float32)
    for f in (2, 4):
        for method in mr.UPSAMPLING:
            for av in (False, True):
                up = mr.upsample(c, f, 5 * f - 1, 7 * f, method, av)
                assert up.shape == (5 * f - 1, 7 * f, 2)
                assert np.allclose(up, 0.3, atol=1e-6)
    # a linear ramp in the block centres' coordinate is reproduced exactly inside
    f = 4
    y = (np.arange(6) * f + (f - 1) / 2.0)
    ramp = np.broadcast_to(y[:, None, None], (6, 3, 1)).astype(np.float32)
    for method in mr.UPSAMPLING:
        up = mr.upsample(ramp, f, 6 * f, 3 * f, method)
        inner = slice(2 * f, 4 * f)                  # two samples from the clamped edges
        assert np.allclose(up[inner, 0, 0], np.arange(6 * f, dtype=np.float32)[inner], atol=1e-4)


def _erode(mask, n):
    """``mask`` shrunk by n px (a square's reach)."""
    out = mask.copy()
    for _ in range(n):
        e = out.copy()
        e[1:] &= out[:-1]
        e[:-1] &= out[1:]
        e[:, 1:] &= out[:, :-1]
        e[:, :-1] &= out[:, 1:]
        out = e
    return out


@pytest.mark.parametrize("occlusion", [True, False])
def test_multires_matches_the_exact_path_within_the_stated_bound(case, occlusion):
    lens, geom, lib, img, depth = case
    ex = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occlusion), library=lib).image
    res = bokeh(img, depth, lens,
                BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occlusion, multires=2.0, max_level=2),
                library=lib)
    levels = res.info["layer_levels"] if occlusion else res.info["multires_patches_per_level"]
    assert sum(sum(lv[1:]) for lv in levels) > 0 if occlusion else sum(levels[1:]) > 0     # some of it coarse
    peak = float(img.max())
    # the bound the report states for levels 1-2 on this kind of scene (docs/performance.md)
    assert psnr(res.image / peak, ex / peak) >= 35.0
    kept = (depth >= 1.1) & (depth <= 1.3)
    if occlusion:                # the kept subject stays sharp where the exact path leaves it (no nearer layer)
        # (the coarse near layer's blur reaches up to the cubic's two samples, 2 x 4 px, further)
        untouched = _erode(kept & (np.abs(ex - img).max(axis=-1) < 1e-6), 8)
        assert untouched.sum() > 50 and np.abs(res.image - img)[untouched].max() < 1e-5
    assert np.isfinite(res.image).all() and res.image.min() >= 0.0


@pytest.mark.parametrize("occlusion", [True, False])
def test_constant_image_stays_constant(case, occlusion):
    lens, geom, lib, _, depth = case
    img = np.full((H, W, 3), 0.7, np.float32)
    res = bokeh(img, depth, lens,
                BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occlusion, multires=1.0, max_level=3),
                library=lib)
    assert np.abs(res.image - 0.7).max() < 2e-4


def _stiff(case):
    _, _, _, img, depth = case
    one_pixel = np.full((H, W), 8.0)
    one_pixel[50, 70] = 0.5
    bright = np.zeros((H, W, 3), np.float32)
    bright[40, 60] = 100.0
    bad = depth.copy()
    bad[:10] = np.nan
    bad[10:20] = 0.0
    bad[20:25] = -1.0
    return {
        "one layer": (img, np.full((H, W), 3.0)),
        "all far": (img, np.full((H, W), 1e10)),
        "infinity": (img, np.full((H, W), np.inf)),
        "invalid depths": (img, bad),
        "zeros": (np.zeros((H, W, 3), np.float32), depth),
        "single bright pixel": (bright, np.full((H, W), 0.5)),
        "one-pixel layer": (img, one_pixel),
    }


@pytest.mark.parametrize("name", ["one layer", "all far", "infinity", "invalid depths", "zeros",
                                  "single bright pixel", "one-pixel layer"])
@pytest.mark.parametrize("occlusion", [True, False])
def test_no_nan_on_stiff_cases(case, name, occlusion):
    lens, geom, lib, _, _ = case
    img, depth = _stiff(case)[name]
    res = bokeh(img, depth, lens,
                BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occlusion, multires=1.0, max_level=3),
                library=lib)
    assert np.isfinite(res.image).all() and res.image.min() >= 0.0
    if name == "single bright pixel":   # the energy of the exact path (+ the clamped undershoot: module docstring)
        ex = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occlusion),
                   library=lib).image
        assert abs(float(res.image.sum()) - float(ex.sum())) < 0.03 * float(ex.sum())
    if name == "zeros":
        assert not res.image.any()


def test_bad_parameters_are_refused_before_work(case):
    lens, geom, lib, img, depth = case
    with pytest.raises(InputRangeError):
        bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, multires=-1.0), library=lib)
    with pytest.raises(InputRangeError):
        bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, multires=2.0, convolution="lowrank"),
              library=lib)


def test_narrow_kernels_at_a_coarse_pitch_stay_at_full_resolution():
    """6P on a 120 x 160 frame spanning its sensor (the report's depth-edge
    case: 16x the pitch of 1920 px): its kernels' half-energy radius is under
    4 px, so the bench's rule (c 4) and even c 2 keep every patch at level 0."""
    lens = load_lens("6p")
    geom = ImageGeometry.full_sensor(lens, 120, 160)
    lib = PSFLibrary(lens, PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=21, band_nm=(400.0, 700.0),
                                       pixel_pitch_mm=geom.pixel_pitch_mm), LibraryGrid(n_fields=8, n_depths=4), None)
    rng = np.random.default_rng(1)
    img = rng.random((120, 160, 3)).astype(np.float32)
    depth = np.where(rng.random((120, 160)) < 0.5, 0.8, 1e10)
    for occ in (True, False):
        ex = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occ, convolution="windows"),
                   library=lib)
        for c in (mr.BENCH_C, 2.0):
            res = bokeh(img, depth, lens, BokehOptions(keep=(1.1, 1.3), geometry=geom, occlusion=occ, multires=c),
                        library=lib)
            levels = res.info["layer_levels"] if occ else [res.info["multires_patches_per_level"]]
            assert all(sum(lv[1:]) == 0 for lv in levels)
            assert np.abs(res.image - ex.image).max() <= 1e-6 * float(np.abs(ex.image).max())   # float32 rounding


def test_cubic_from_block_means_is_closer_than_bilinear_on_a_blurred_image():
    rng = np.random.default_rng(2)
    x = rng.random((128, 128, 1))
    fy = np.fft.fftfreq(128)[:, None]
    fx = np.fft.fftfreq(128)[None, :]
    for sigma in (2.0, 4.0):                                     # a Gaussian blur of sigma px (periodic)
        g = np.exp(-2 * (np.pi * sigma) ** 2 * (fy ** 2 + fx ** 2))[..., None]
        b = np.real(np.fft.ifft2(np.fft.fft2(x, axes=(0, 1)) * g, axes=(0, 1))).astype(np.float32)
        for f in (2, 4):
            c = mr.block_mean(b, f)
            inner = (slice(16, -16), slice(16, -16))
            err = {m: np.abs(mr.upsample(c, f, 128, 128, m, m == "cubic") - b)[inner].max() for m in mr.UPSAMPLING}
            assert err["cubic"] < err["linear"]
