"""PSNR and SSIM (numpy and torch) against scikit-image (a test-only reference)."""
import numpy as np
import pytest

from dcdi_core.models.common import metrics as M
from dcdi_core.errors import InputRangeError

skm = pytest.importorskip("skimage.metrics")


def _pair(shape, seed, noise=0.1):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    return a, np.clip(a + noise * rng.standard_normal(shape), 0.0, 1.0)


def _ref_ssim(a, b, data_range, channel_axis=None):
    return skm.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=data_range, channel_axis=channel_axis)


@pytest.mark.parametrize("shape,seed", [((41, 41), 0), ((3, 41, 41), 1), ((3, 11, 11), 2), ((3, 67, 53), 3)])
def test_ssim_and_psnr_equal_scikit_image(shape, seed):
    a, b = _pair(shape, seed)
    ch = 0 if len(shape) == 3 else None
    for L, (x, y) in ((1.0, (a, b)), (255.0, (M.quantize_8bit(a), M.quantize_8bit(b)))):
        assert M.ssim(x, y, L) == pytest.approx(_ref_ssim(x, y, L, ch), abs=1e-4)
        assert M.psnr(x, y, L) == pytest.approx(skm.peak_signal_noise_ratio(x, y, data_range=L), abs=1e-4)


def test_ssim_of_psf_like_images_and_batches():
    # sparse, peaky images (PSFs) and a batch: one value per image
    rng = np.random.default_rng(4)
    a = np.zeros((5, 3, 41, 41))
    a[:, :, 18:23, 18:23] = rng.random((5, 3, 5, 5))
    b = np.clip(a + 0.01 * rng.standard_normal(a.shape), 0, None)
    got = M.ssim(a, b, 1.0)
    assert got.shape == (5,)
    for i in range(5):
        assert got[i] == pytest.approx(_ref_ssim(a[i], b[i], 1.0, 0), abs=1e-4)
    assert M.ssim(a[0], a[0], 1.0) == pytest.approx(1.0)
    assert M.psnr(a[0], a[0], 1.0) == np.inf


def test_torch_versions_equal_numpy():
    torch = pytest.importorskip("torch")
    a, b = _pair((4, 3, 41, 41), 5)
    ta, tb = torch.tensor(a), torch.tensor(b)
    assert np.allclose(M.ssim_torch(ta, tb, 1.0).numpy(), M.ssim(a, b, 1.0), atol=1e-10)
    assert np.allclose(M.psnr_torch(ta, tb, 1.0).numpy(), M.psnr(a, b, 1.0), atol=1e-10)
    ta.requires_grad_(True)
    (1 - M.ssim_torch(ta, tb, 1.0).mean()).backward()       # usable as a loss
    assert torch.isfinite(ta.grad).all()


def test_errors_name_the_argument():
    a, b = _pair((3, 41, 41), 6)
    with pytest.raises(InputRangeError, match="data_range"):
        M.ssim(a, b, 0)
    with pytest.raises(InputRangeError, match="shapes"):
        M.psnr(a, b[:, :40], 1.0)
    with pytest.raises(InputRangeError, match="SSIM window"):
        M.ssim(a[:, :9, :9], b[:, :9, :9], 1.0)


def test_psf_scores_scales():
    rng = np.random.default_rng(7)
    ref = rng.random((6, 3, 15, 15)) ** 8
    ref /= ref.sum(axis=(-1, -2), keepdims=True)
    s = M.psf_scores(ref, ref, scale="sum")
    assert s["rel_l1"] == 0 and s["ssim_8bit"] == pytest.approx(1.0) and s["psnr_8bit"] == 100.0
    peak = ref / ref.max(axis=(-1, -2), keepdims=True)
    same = M.psf_scores(peak, ref, scale="peak")              # the paper's output scale: same figures
    assert same == {k: pytest.approx(v, abs=1e-12) for k, v in s.items()}
    worse = M.psf_scores(ref + 1e-3, ref, scale="sum")
    assert 0 < worse["rel_l1"] and worse["psnr_sum"] < 100


def test_psf_scores_say_how_the_psnr_spreads():
    """One bad PSF among exact ones: the capped mean stays high, the worst says it."""
    rng = np.random.default_rng(3)
    ref = rng.random((10, 3, 15, 15)) ** 8
    ref /= ref.sum(axis=(-1, -2), keepdims=True)
    pred = ref.copy()
    pred[4] = np.roll(ref[4], 3, axis=-1)
    s = M.psf_scores(pred, ref, scale="sum")
    assert s["psnr_8bit_median"] == 100.0 and s["psnr_8bit"] > 90.0 and s["psnr_8bit_worst"] < 30.0, s
