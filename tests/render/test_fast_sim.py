"""The simulation's fast paths (issue 15) against the exact ones they replace.

'fast' convolution and PSF map, and the torch accelerator, compute what the
windows method and the former rotation compute: equal to float32 rounding
(the report's 'max abs diff vs windows' column). Stiff inputs give no NaN.
"""
import sys

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render import accel_torch
from dcdi_core.render.convolve import ConvolveOptions, patch_convolve
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import _rotate_flat, _rotate_flat_fast, psf_map
from dcdi_core.render.simulate import SimulateOptions, simulate

FAST = PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=21)
ROUNDING = 2e-6          # float32 rounding of sums of O(100) terms of values <= 1
needs_torch = pytest.mark.skipif(not accel_torch.available(), reason="torch is not installed here")


def _kernels(rng, nph, npw, k):
    """Random non-negative kernels of varied width, each channel summing to 1."""
    r = k // 2
    d2 = (np.arange(k) - r)[:, None] ** 2 + (np.arange(k) - r)[None, :] ** 2
    ker = rng.uniform(0, 1, (nph, npw, 3, k, k)).astype(np.float32)
    ker *= np.exp(-d2 / rng.uniform(0.5, 40.0, (nph, npw, 1, 1, 1))).astype(np.float32)
    return ker / ker.sum(axis=(-2, -1), keepdims=True)


@pytest.mark.parametrize("h,w,m,k,blend,backend", [
    (50, 70, 8, 9, None, None), (37, 41, 16, 21, None, "numpy"), (64, 96, 16, 41, 4, None),
    (40, 56, 16, 31, 6, "numpy"), (1, 5, 2, 3, None, None), (5, 1, 4, 5, None, "numpy"), (1, 1, 2, 5, None, None)])
def test_fast_equals_windows(h, w, m, k, blend, backend):
    rng = np.random.default_rng(h * 100 + w)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    nph, npw = -(-h // m), -(-w // m)
    ker = _kernels(rng, nph, npw, k)
    ident = rng.uniform(size=(nph, npw)) < 0.2
    for pairs in (None, ((0, 0), (1, 1), (2, 2), (0, 1), (2, 0))):
        want = patch_convolve(img, ker, m, ConvolveOptions(blend=blend, fft_backend=backend), identity=ident,
                              pairs=pairs)
        got = patch_convolve(img, ker, m, ConvolveOptions(blend=blend, fft_backend=backend, method="fast"),
                             identity=ident, pairs=pairs)
        assert got.shape == want.shape and got.dtype == np.float32
        assert np.abs(got - want).max() <= ROUNDING


def test_fast_skips_empty_parts_and_keeps_constants():
    rng = np.random.default_rng(3)
    ker = _kernels(rng, 5, 7, 21)
    x = rng.uniform(0, 1, (80, 112, 4)).astype(np.float32)
    x[:, 70:] = 0.0                                       # an empty part, as a depth layer has
    pairs = ((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2))
    got = patch_convolve(x, ker, 16, ConvolveOptions(method="fast"), pairs=pairs)
    assert np.abs(got - patch_convolve(x, ker, 16, pairs=pairs)).max() <= ROUNDING
    assert np.abs(got[:, 104:]).max() == 0.0              # windows there read no content: skipped
    one = np.ones((80, 112, 3), np.float32)
    for b in (8, 6, 4):
        assert np.abs(patch_convolve(one, ker, 16, ConvolveOptions(blend=b, method="fast")) - 1.0).max() < 1e-5


@pytest.mark.parametrize("k", [1, 3, 5, 13, 25])
def test_fast_rotation_equals_former(k):
    rng = np.random.default_rng(k)
    n = 64
    src = (rng.uniform(0, 1, (n, 3, k * k)) ** 4).astype(np.float32)
    src[:, :, (k // 2) * k + k // 2] += rng.uniform(0, 3, (n, 3)).astype(np.float32)     # peaked centres
    ang = rng.uniform(-np.pi, np.pi, n)
    out = np.stack([np.cos(ang), np.sin(ang)], -1)
    out[:4] = [[1, 0], [0, 1], [-1, 0], [np.sqrt(0.5), -np.sqrt(0.5)]]                   # axis-aligned, 45 deg
    want = _rotate_flat(src, out, k, src.sum(-1))
    assert np.abs(_rotate_flat_fast(src, out, k, src.sum(-1)) - want).max() <= 1e-6 * np.abs(want).max()
    if accel_torch.available():
        import torch
        got = accel_torch.rotate_flat(torch.from_numpy(src), torch.from_numpy(out.astype(np.float32)), k,
                                      torch.from_numpy(src.sum(-1))).numpy()
        assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max()


@pytest.fixture(scope="module")
def scene():
    lens = load_lens("mos-s1")
    h, w = 48, 72
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122, center_px=(-60.0, -90.0))     # off axis
    s = PSFSettings(**{**FAST.as_dict(), "band_nm": (400.0, 700.0), "pixel_pitch_mm": geom.pixel_pitch_mm})
    lib = PSFLibrary(lens, s, LibraryGrid(n_fields=8, n_depths=4), None)
    rng = np.random.default_rng(5)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    depth = rng.uniform(0.3, 30.0, (h, w))
    depth[:10, :10] = np.nan                              # one patch without valid depth
    lib.ensure(depth[np.isfinite(depth)], clamp_near=True)
    return lens, geom, lib, img, depth


def test_fast_psf_map_equals_exact(scene):
    lens, geom, lib, img, depth = scene
    want = psf_map(lib, geom, depth, 8, method="exact")
    got = psf_map(lib, geom, depth, 8)
    assert np.abs(got.kernels - want.kernels).max() <= 1e-6
    assert (got.identity == want.identity).all()
    # the kernels are zero outside the square the map says it computed
    r = lib.kernel_size // 2
    for (i, j), h in np.ndenumerate(got.support_px):
        ring = np.ones((lib.kernel_size,) * 2, bool)
        ring[r - h:r + h + 1, r - h:r + h + 1] = False
        assert not got.kernels[i, j][:, ring].any()


def test_cropped_psf_map_is_the_full_maps_centre(scene):
    lens, geom, lib, img, depth = scene
    for far in (False, True):        # the near depths' wide kernels, and a far plane's narrow ones
        d = np.full_like(depth, 30.0) if far else depth
        full = psf_map(lib, geom, d, 8)
        got = psf_map(lib, geom, d, 8, crop=True)
        k, r = got.kernels.shape[-1], lib.kernel_size // 2
        assert k == 2 * int(got.support_px.max()) + 1 and k <= lib.kernel_size and (k < lib.kernel_size or not far)
        h = k // 2
        assert np.array_equal(got.kernels, full.kernels[..., r - h:r + h + 1, r - h:r + h + 1])
        outside = np.ones((lib.kernel_size,) * 2, bool)
        outside[r - h:r + h + 1, r - h:r + h + 1] = False
        assert not full.kernels[..., outside].any()                  # nothing was cut off
    none = psf_map(lib, geom, np.full_like(depth, np.nan), 8, crop=True)     # nothing to blur: 1 x 1 identities
    assert none.kernels.shape[-1] == 1 and (none.kernels == 1).all()


def test_simulate_fast_default_equals_windows(scene):
    lens, geom, lib, img, depth = scene
    want = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, convolution="windows"), library=lib).image
    for backend in (None, "numpy"):
        got = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, fft_backend=backend), library=lib).image
        assert np.abs(got - want).max() <= ROUNDING


@needs_torch
def test_torch_equals_numpy(scene):
    lens, geom, lib, img, depth = scene
    a = psf_map(lib, geom, depth, 8)
    b = psf_map(lib, geom, depth, 8, accelerator="torch")
    assert np.abs(a.kernels - b.kernels).max() <= 1e-5 and (a.support_px == b.support_px).all()
    want = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=lib).image
    got = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, accelerator="torch"), library=lib).image
    assert got.dtype == np.float32 and np.abs(got - want).max() <= 1e-5
    rng = np.random.default_rng(9)
    ker = _kernels(rng, 3, 4, 21)
    x = rng.uniform(0, 1, (40, 60, 4)).astype(np.float32)
    pairs = ((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2))
    want = patch_convolve(x, ker, 16, ConvolveOptions(method="fast", blend=6), pairs=pairs)
    got = patch_convolve(x, ker, 16, ConvolveOptions(method="fast", blend=6, accelerator="torch"), pairs=pairs)
    assert np.abs(got - want).max() <= ROUNDING


def test_torch_blocked_numpy_runs(scene, monkeypatch):
    lens, geom, lib, img, depth = scene
    monkeypatch.setitem(sys.modules, "torch", None)       # `import torch` now raises ImportError
    assert not accel_torch.available()
    with pytest.raises(InputRangeError, match="accelerator"):
        simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, accelerator="torch"), library=lib)
    with pytest.raises(InputRangeError, match="accelerator"):
        psf_map(lib, geom, depth, 8, accelerator="torch")
    with pytest.raises(ValueError, match="torch"):
        patch_convolve(img, np.zeros((6, 9, 3, 5, 5), np.float32), 8,
                       ConvolveOptions(method="fast", accelerator="torch"))
    r = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=lib)
    assert np.isfinite(r.image).all()


def test_bad_options_refused_before_work(scene):
    lens, geom, lib, img, depth = scene
    for kw, field in ((dict(convolution="lowrank"), "convolution"), (dict(accelerator="cuda"), "accelerator"),
                      (dict(convolution="windows", accelerator="torch"), "accelerator"), (dict(blend=9), "blend")):
        with pytest.raises(InputRangeError, match=field):
            simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False, **kw), library=lib)
    with pytest.raises(InputRangeError, match="method"):
        psf_map(lib, geom, depth, 8, method="quick")


@pytest.mark.parametrize("accelerator", [None, pytest.param("torch", marks=needs_torch)])
def test_stiff_inputs_no_nan(scene, accelerator):
    lens, geom, lib, img, depth = scene
    h, w = img.shape[:2]

    def run(x, d, g=geom):
        out = simulate(x, d, lens, SimulateOptions(geometry=g, distortion=False, accelerator=accelerator),
                       library=lib).image
        assert out.shape == x.shape and np.isfinite(out).all() and (out >= 0).all()
        want = simulate(x, d, lens, SimulateOptions(geometry=g, distortion=False, convolution="windows"),
                        library=lib).image
        assert np.abs(out - want).max() <= 1e-5
        return out

    assert run(np.zeros_like(img), depth).max() == 0.0
    dot = np.zeros_like(img)
    dot[24, 36] = 1.0
    assert run(dot, np.full((h, w), 5.0)).max() > 0.0
    from dcdi_core.errors import RenderError
    with pytest.raises(RenderError, match="no valid depth"):             # refused before any work, as today
        run(img, np.full((h, w), np.nan))
    pm = psf_map(lib, geom, np.full((h, w), np.nan), 8, accelerator=accelerator)    # all identity: copied
    assert pm.identity.all()
    got = patch_convolve(img, pm.kernels, 8, ConvolveOptions(method="fast", accelerator=accelerator),
                         identity=pm.identity)
    assert np.abs(got - img).max() <= ROUNDING
    for hh, ww in ((1, 1), (1, 9), (7, 1)):
        g = ImageGeometry.from_pixel_pitch(lens, hh, ww, 0.0122, center_px=(-60.0, -90.0))
        run(np.full((hh, ww, 3), 0.5, np.float32), np.full((hh, ww), 2.0), g)


def test_blas_runs_on_one_thread_inside_the_pools_blocks():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from dcdi_core.parallel import one_blas_thread
    np.ones((4, 4)) @ np.ones((4, 4))                       # BLAS loaded
    blas = [i for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
    if not blas:
        pytest.skip("numpy's BLAS is not visible to threadpoolctl here")
    before = [i["num_threads"] for i in blas]
    with one_blas_thread():
        assert all(i["num_threads"] == 1 for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")
    assert [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"] == before


def test_grow_square_is_the_square_dilation():
    from dcdi_core.render.windows import grow_square
    rng = np.random.default_rng(1)
    for n in (0, 1, 3, 20):
        mask = rng.random((9, 13)) < 0.05
        padded, want = np.pad(mask, n), np.zeros_like(mask)
        for u in range(2 * n + 1):
            for v in range(2 * n + 1):
                want |= padded[u:u + 9, v:v + 13]
        assert np.array_equal(grow_square(mask, n), want)
