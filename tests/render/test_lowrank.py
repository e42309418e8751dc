"""patch_convolve with ConvolveOptions(method='lowrank') against the exact per-window path: the stated bound holds."""
import numpy as np
import pytest

from dcdi_core.render.convolve import ConvolveOptions, low_rank, patch_convolve


def _kernels(nph, npw, k=21):
    """Anisotropic Gaussians rotating with the patch azimuth and growing across the image, per channel."""
    r = k // 2
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    kern = np.zeros((nph, npw, 3, k, k), np.float32)
    for i in range(nph):
        for j in range(npw):
            th = np.arctan2(i - nph / 2, j - npw / 2)
            u, v = x * np.cos(th) + y * np.sin(th), -x * np.sin(th) + y * np.cos(th)
            for c in range(3):
                g = np.exp(-(u / (1 + 0.3 * i + 0.2 * c)) ** 2 / 2 - (v / (0.7 + 0.1 * j)) ** 2 / 2)
                kern[i, j, c] = g / g.sum()
    return kern


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(0)
    h, w, m = 100, 130, 16
    kern = _kernels(-(-h // m), -(-w // m))
    ident = np.zeros(kern.shape[:2], bool)
    ident[2, 3] = True
    return rng.random((h, w, 3)).astype(np.float32), kern, ident, m


@pytest.mark.parametrize("eps,tile,backend", [(0.0, 4, None), (1e-2, 4, None), (5e-2, 8, None), (1e-1, 3, None),
                                              (1e-2, 4, "numpy")])
def test_lowrank_within_bound(case, eps, tile, backend):
    img, kern, ident, m = case
    exact = patch_convolve(img, kern, m, ConvolveOptions(support_eps=0.0, fft_backend="numpy"), identity=ident)
    lowrank = ConvolveOptions(support_eps=0.0, method="lowrank", rank_eps=eps, tile=tile, fft_backend=backend)
    got = patch_convolve(img, kern, m, lowrank, identity=ident)
    bound = 2 * eps / (1 - eps) * float(np.abs(img).max()) + 2e-6
    assert got.shape == exact.shape and got.dtype == np.float32
    assert np.abs(got - exact).max() <= bound


def test_lowrank_constant_pairs_and_zero(case):
    img, kern, ident, m = case
    one = np.ones_like(img)
    lowrank = ConvolveOptions(method="lowrank", rank_eps=0.1)
    assert np.abs(patch_convolve(one, kern, m, lowrank, identity=ident) - 1).max() < 1e-5
    pairs = ((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2))
    x4 = np.concatenate([img, img[..., :1]], -1)
    x4[:, 70:] = 0                                     # an empty part, as a depth layer has
    exact = patch_convolve(x4, kern, m, pairs=pairs)
    got = patch_convolve(x4, kern, m, ConvolveOptions(method="lowrank", rank_eps=1e-2), pairs=pairs)
    assert np.abs(got - exact).max() <= 2 * 1e-2 / 0.99 + 1e-5
    assert np.abs(got[:, 120:]).max() == 0.0           # beyond any kernel's reach of the content


def test_low_rank_rows_within_eps():
    rng = np.random.default_rng(1)
    a = np.abs(rng.normal(size=(12, 3)) @ rng.normal(size=(3, 50)) + 0.01 * rng.random((12, 50))).astype(np.float32)
    for eps in (0.0, 1e-3, 1e-1):
        coef, basis = low_rank(a, eps)
        err = np.abs(a - coef @ basis).sum(axis=1)
        assert (err <= eps * np.abs(a).sum(axis=1) + 1e-5).all()
    assert low_rank(a, 0.3)[1].shape[0] < len(a)       # a true reduction


def test_lowrank_refuses_bad_arguments(case):
    img, kern, _, m = case
    with pytest.raises(ValueError):
        patch_convolve(img, kern, m, ConvolveOptions(method="svd"))
    with pytest.raises(ValueError):
        patch_convolve(img, kern, m, ConvolveOptions(method="lowrank", tile=0))


def test_bokeh_lowrank_matches_windows_within_the_bound():
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.psf.library import LibraryGrid, PSFLibrary
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.bokeh import BokehOptions, bokeh

    lens = load_lens("mos-s1")
    h, w = 64, 96
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122)
    lib = PSFLibrary(lens, PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=21, band_nm=(400.0, 700.0),
                                       pixel_pitch_mm=0.0122), LibraryGrid(n_fields=8, n_depths=4), None)
    img = np.random.default_rng(5).random((h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 8.0)
    depth[20:44, 30:60] = 1.0
    eps = 1e-2
    plain = [bokeh(img, depth, lens,
                   BokehOptions(keep=(0.9, 1.1), geometry=geom, occlusion=False, convolution=c, rank_eps=eps),
                   library=lib).image for c in ("windows", "lowrank")]
    assert np.abs(plain[0] - plain[1]).max() <= 2 * eps / (1 - eps) * img.max() + 1e-5
    layered = [bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom, convolution=c, rank_eps=eps),
                     library=lib).image for c in ("windows", "lowrank")]
    assert np.abs(layered[1][20:44, 30:60] - img[20:44, 30:60]).max() < 1e-6      # the kept subject untouched
    assert np.abs(layered[0] - layered[1]).mean() < 2 * eps * img.max()
    with pytest.raises(Exception):
        bokeh(img, depth, lens, BokehOptions(keep=(0.9, 1.1), geometry=geom, convolution="svd"), library=lib)
