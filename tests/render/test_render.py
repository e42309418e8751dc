"""Patch-wise simulation and bokeh: identity, energy, a point source, seams, depth handling."""

from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render.convolve import ConvolveOptions, patch_convolve
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import identity_kernel, psf_map
from dcdi_core.render.bokeh import BokehOptions, bokeh
from dcdi_core.render.simulate import SimulateOptions, simulate

FAST = PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=21)


@pytest.fixture(scope="module")
def lens():
    return load_lens("mos-s1")


def _lib(lens, geom, **kw):
    s = PSFSettings(**{**FAST.as_dict(), "band_nm": (400.0, 700.0), "pixel_pitch_mm": geom.pixel_pitch_mm, **kw})
    return PSFLibrary(lens, s, LibraryGrid(n_fields=8, n_depths=4), None)


def _geom(lens, h, w):
    # a small image covering the central part of the sensor at the sensor's own pitch
    return ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122)


def test_full_image_convolution_matches_patchwise_with_one_kernel():
    rng = np.random.default_rng(0)
    img = rng.random((45, 70, 3)).astype(np.float32)
    k = 9
    kern = rng.random((3, k, k))
    kern /= kern.sum(axis=(1, 2), keepdims=True)
    out = patch_convolve(img, np.broadcast_to(kern, (3, 5, 3, k, k)), 16)
    r = k // 2
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="reflect")
    ref = np.zeros_like(img)
    for c in range(3):
        for dy in range(k):
            for dx in range(k):
                ref[..., c] += kern[c, dy, dx] * pad[2 * r - dy:2 * r - dy + 45, 2 * r - dx:2 * r - dx + 70, c]
    assert np.abs(out - ref).max() < 1e-5


def test_identity_psf_returns_the_image():
    img = np.random.default_rng(1).random((33, 47, 3)).astype(np.float32)
    kern = np.broadcast_to(identity_kernel(11), (3, 3, 3, 11, 11))
    assert np.abs(patch_convolve(img, kern, 16) - img).max() < 1e-6


@pytest.mark.parametrize("shape", [(64, 96), (37, 53), (5, 7), (1, 1)])
def test_constant_image_stays_constant_odd_sizes(lens, shape):
    h, w = shape
    geom = _geom(lens, h, w)
    depth = np.random.default_rng(2).uniform(0.7, 20.0, size=(h, w))
    img = np.full((h, w, 3), 0.37, np.float32)
    r = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=_lib(lens, geom))
    assert r.image.shape == (h, w, 3) and r.image.dtype == np.float32
    assert np.abs(r.image - 0.37).max() < 1e-5


def test_single_point_reproduces_the_psf(lens):
    h = w = 96
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom)
    img = np.zeros((h, w, 3), np.float32)
    y, x = 40, 57
    img[y, x] = 1.0
    depth = np.full((h, w), 2.0)
    r = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, patch=16), library=lib)
    pm = r.psf_map
    kern = pm.kernels[y // 16, x // 16]                       # the patch's own kernel
    k = kern.shape[-1]
    got = np.moveaxis(r.image[y - k // 2:y + k // 2 + 1, x - k // 2:x + k // 2 + 1], -1, 0)
    # the point sits between patch centres: its kernel is the tent blend of its 4 neighbours'
    # blending neighbouring patches' outputs conserves energy up to how much the kernels vary
    assert abs(got.sum() - 3.0) < 0.03 * 3.0
    assert np.abs(got - kern).max() < 0.25 * kern.max()


def test_no_seam_on_a_smooth_image(lens):
    h, w = 96, 128
    geom = _geom(lens, h, w)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([0.3 + 0.2 * np.sin(xx / 17.0), 0.5 + 0.1 * np.cos(yy / 23.0), 0.4 + 0.001 * xx], -1).astype(np.float32)
    depth = 1.0 + 4.0 * xx / w                                   # depth varies across patches
    r = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=_lib(lens, geom))
    # the second difference across a patch border is no larger than inside patches
    d2 = np.abs(r.image[:, 2:] - 2 * r.image[:, 1:-1] + r.image[:, :-2]).mean(axis=(0, 2))
    cols = np.arange(1, w - 1)
    border = d2[(cols % 16 == 0) | (cols % 16 == 15)]
    inner = d2[(cols % 16 > 2) & (cols % 16 < 13)]
    assert border.max() < 2.0 * inner.max() + 1e-6


def test_invalid_and_far_depths(lens):
    h, w = 32, 48
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom)
    depth = np.full((h, w), 1e10)
    depth[:16, :16] = np.nan
    depth[:16, 16:32] = 0.0
    depth[16:, :16] = -3.0
    depth[16:, 16:32] = np.inf
    pm = psf_map(lib, geom, depth, 16)
    assert pm.identity[0, 0] and pm.identity[0, 1] and pm.identity[1, 0]     # no valid depth: left sharp
    assert pm.info["no_valid_depth"] == 3
    assert np.isfinite(pm.kernels).all()
    # inf, 1e10 and anything beyond the far limit all take the infinity PSF
    maps = [psf_map(lib, geom, np.full((h, w), v), 16).kernels for v in (np.inf, 1e10, 50.0)]
    assert np.array_equal(maps[0], maps[1]) and np.array_equal(maps[0], maps[2])


def test_depth_unaware_baseline_uses_one_depth(lens):
    h, w = 32, 32
    geom = _geom(lens, h, w)
    depth = np.random.default_rng(3).uniform(0.8, 9.0, (h, w))
    img = np.random.default_rng(4).random((h, w, 3)).astype(np.float32)
    lib = _lib(lens, geom)
    aware = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=lib)
    fixed = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=lib, fixed_depth_m=2.0)
    assert np.isfinite(fixed.image).all()
    assert np.nanstd(fixed.psf_map.depth_m) == 0.0 and np.nanstd(aware.psf_map.depth_m) > 0
    assert not fixed.info["depth_aware"]


def test_bokeh_keeps_the_kept_range_unchanged(lens):
    h, w = 64, 96
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom, focus_distance_m=None)
    rng = np.random.default_rng(5)
    img = rng.random((h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 8.0)                  # background far
    depth[20:44, 30:60] = 1.0                      # subject, kept sharp
    for occ in (True, False):
        r = bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom, occlusion=occ), library=lib)
        inside = r.image[20:44, 30:60]
        if occ:   # nothing nearer covers the subject: exactly unchanged
            assert np.abs(inside - img[20:44, 30:60]).max() < 1e-6
        bg = r.image[:, :20]
        assert np.abs(bg - img[:, :20]).mean() > 0.01       # the background is blurred
    with pytest.raises(InputRangeError):
        bokeh(img, depth, lens, BokehOptions(geometry=geom), library=lib)


def test_bokeh_cancelled_callback_stops_between_layers(lens):
    from dcdi_core.render.base import Cancelled
    h, w = 64, 96
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom, focus_distance_m=None)
    img = np.random.default_rng(6).random((h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 8.0)
    depth[:, :30] = 3.0
    depth[20:44, 30:60] = 1.0
    calls = []
    ref = bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom), library=lib,
                cancelled=lambda: calls.append(1) and False)
    assert len(calls) >= 2                               # asked before every blurred layer
    again = bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom), library=lib)
    assert np.array_equal(ref.image, again.image)
    for occ in (True, False):
        asked = []
        with pytest.raises(Cancelled):
            bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom, occlusion=occ), library=lib,
                  cancelled=lambda: asked.append(1) or len(asked) >= (2 if occ else 1))
        assert len(asked) == (2 if occ else 1)           # stopped at once, no further layer


def _direct(img, kern):
    """Reference: full-image spatial convolution with one kernel, reflect border."""
    k = kern.shape[-1]
    r = k // 2
    h, w = img.shape[:2]
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="reflect")
    ref = np.zeros_like(img)
    for dy in range(k):
        for dx in range(k):
            ref += kern[:, dy, dx] * pad[2 * r - dy:2 * r - dy + h, 2 * r - dx:2 * r - dx + w]
    return ref


def test_kernel_support_is_the_square_that_holds_the_energy():
    from dcdi_core.render.convolve import kernel_support

    k = 11
    kern = np.zeros((2, 3, k, k), np.float32)
    kern[0, :, 5, 5] = 1.0                                # a delta: half-width 0
    kern[1, :, 5, 5] = 0.99
    kern[1, 1, 5, 8] = 0.01                               # 1 % of one channel 3 px out
    assert kernel_support(kern, 0.0).tolist() == [0, 3]
    assert kernel_support(kern, 0.02).tolist() == [0, 0]   # 1 % < 2 %: cropped
    assert kernel_support(kern, 0.005).tolist() == [0, 3]


def test_cropped_support_matches_the_full_kernel_with_a_small_psf_in_a_large_kernel():
    """A 5 x 5 blur stored in 41 x 41: the crop (a smaller FFT) gives the same image."""
    rng = np.random.default_rng(6)
    img = rng.random((40, 56, 3)).astype(np.float32)
    small = rng.random((3, 5, 5)).astype(np.float32)
    small /= small.sum(axis=(1, 2), keepdims=True)
    big = np.zeros((3, 41, 41), np.float32)
    big[:, 18:23, 18:23] = small
    out = patch_convolve(img, np.broadcast_to(big, (3, 4, 3, 41, 41)), 16, ConvolveOptions(support_eps=0.0))
    assert np.abs(out - _direct(img, small)).max() < 1e-5


@pytest.mark.parametrize("eps", [1e-3, 1e-2])
def test_support_crop_error_is_bounded_by_eps_and_constants_stay_constant(eps):
    """A wide Gaussian tail: cropping moves at most ~eps of the energy and keeps each kernel's sum."""
    k = 31
    yy, xx = np.mgrid[-15:16, -15:16]
    g = np.exp(-(yy ** 2 + xx ** 2) / (2 * 4.0 ** 2)).astype(np.float32)
    kern = np.broadcast_to(g / g.sum(), (3, k, k))
    rng = np.random.default_rng(7)
    img = rng.random((48, 64, 3)).astype(np.float32)
    out = patch_convolve(img, np.broadcast_to(kern, (3, 4, 3, k, k)), 16, ConvolveOptions(support_eps=eps))
    assert np.abs(out - _direct(img, kern)).max() < 2 * eps
    const = patch_convolve(np.full((48, 64, 3), 0.5, np.float32), np.broadcast_to(kern, (3, 4, 3, k, k)), 16,
                           ConvolveOptions(support_eps=eps))
    assert np.abs(const - 0.5).max() < 1e-5


def test_fft_backends_agree():
    from dcdi_core.render import fft

    if fft._sfft is None:
        pytest.skip("scipy not installed: only the numpy backend exists here")
    rng = np.random.default_rng(8)
    img = rng.random((50, 70, 3)).astype(np.float32)
    kern = rng.random((4, 5, 3, 15, 15)).astype(np.float32)
    kern /= kern.sum(axis=(-2, -1), keepdims=True)
    fast = patch_convolve(img, kern, 16)
    assert fft.backend() == "scipy" and fft.backend("numpy") == "numpy"
    slow = patch_convolve(img, kern, 16, ConvolveOptions(fft_backend="numpy"))
    assert fft.backend() == "scipy"                     # a parameter: nothing process-wide changed
    assert np.abs(fast - slow).max() < 1e-5
    with pytest.raises(ValueError, match="allowed scipy, numpy"):
        patch_convolve(img, kern, 16, ConvolveOptions(fft_backend="fftw"))


def test_psf_map_support_crop_matches_the_full_kernels(lens):
    """Kernels computed over their support disk equal the full interpolated, rotated kernels."""
    from dcdi_core.render.psfmap import rotate_radial_kernels

    h, w = 48, 64
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom)
    depth = np.random.default_rng(9).uniform(0.8, 9.0, (h, w))
    pm = psf_map(lib, geom, depth, 16, support_eps=0.0)
    todo = ~pm.identity
    nph, npw = pm.identity.shape
    rr, cc = np.meshgrid(np.minimum(np.arange(nph) * 16 + 7.5, h - 1), np.minimum(np.arange(npw) * 16 + 7.5, w - 1),
                         indexing="ij")
    vec = np.stack([rr[todo] - geom.center_px[0], cc[todo] - geom.center_px[1]], -1)
    ref = rotate_radial_kernels(lib.at(pm.field[todo], pm.depth_m[todo]), vec / np.hypot(*vec.T)[:, None])
    assert np.abs(pm.kernels[todo] - ref).max() < 1e-6
    cropped = psf_map(lib, geom, depth, 16, support_eps=1e-2).kernels[todo]
    assert np.abs(cropped.sum(axis=(-2, -1)) - ref.sum(axis=(-2, -1))).max() < 1e-5
    assert (np.abs(cropped - ref).sum(axis=(-2, -1)) <= 2.5e-2).all()


def test_layered_bokeh_leaves_no_seam_on_a_continuous_surface(lens):
    """A constant image on a depth ramp (a floor crossing every layer) stays
    constant: layers hand over without dark seams at their boundaries."""
    h, w = 96, 64
    geom = _geom(lens, h, w)
    lib = _lib(lens, geom)
    depth = np.repeat(np.linspace(0.8, 9.0, h)[:, None], w, axis=1)
    img = np.full((h, w, 3), 0.5, np.float32)
    opts = BokehOptions(keep=(20.0, 30.0), geometry=geom, occlusion=True, n_layers=6, seam_tol=None)
    r = bokeh(img, depth, lens, opts, library=lib)
    assert r.info["layers"] == 6
    assert np.abs(r.image - 0.5).max() < 1e-3
    # by default the layers of a surface without a depth edge are blurred as
    # one (here 1/95 of the diopter range a row: 6 % of a layer's width)
    even = np.repeat(1.0 / np.linspace(1 / 0.8, 1 / 9.0, h)[:, None], w, axis=1)
    merged = bokeh(img, even, lens, replace(opts, seam_tol=0.25), library=lib)
    assert merged.info["layers"] == 1
    assert np.abs(merged.image - 0.5).max() < 1e-3


def test_open_library_fits_the_kernel_to_the_psfs_the_depths_need(lens):
    import warnings

    from dcdi_core.psf.compute import KernelTooSmallWarning
    from dcdi_core.psf.sources import open_library

    geom = _geom(lens, 64, 96)
    settings = PSFSettings(**{**FAST.as_dict(), "band_nm": (400.0, 700.0)})
    grid = LibraryGrid(n_fields=8, n_depths=4)
    depth = np.full((64, 96), 2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", KernelTooSmallWarning)          # the fitted kernel holds 99 %
        lib = open_library(lens, geom, settings, grid, cache=False, fit_depth_m=depth)
    assert lib.kernel_size > 21 and lib.kernel_size % 2 == 1
    assert lib.kernel_size >= lib.kernel_size_needed[lib.computed].max()
    plain = open_library(lens, geom, settings, grid, cache=False)
    assert plain.kernel_size == 21                                     # no depth map: the settings' size
