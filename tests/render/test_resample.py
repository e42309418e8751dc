"""Resampling at fractional pixel positions (render.resample) and its use in the distortion warps."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.render.distortion import distort, radial_distortion, undistort
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.resample import METHODS, sample
from lab.resample_accuracy import format_warp_accuracy, warp_accuracy

HIGHER = ["keys", "lanczos3", "bspline"]


def former_bilinear(img, y, x):
    """distortion._bilinear as it was before render.resample replaced it."""
    h, w = img.shape[:2]
    y = np.clip(y, 0.0, h - 1.0)
    x = np.clip(x, 0.0, w - 1.0)
    i0 = np.minimum(np.floor(y).astype(np.intp), h - 1)
    j0 = np.minimum(np.floor(x).astype(np.intp), w - 1)
    i1 = np.minimum(i0 + 1, h - 1)
    j1 = np.minimum(j0 + 1, w - 1)
    wy = (y - i0).astype(np.float32)
    wx = (x - j0).astype(np.float32)
    if img.ndim == 3:
        wy, wx = wy[..., None], wx[..., None]
    src = img.astype(np.float32, copy=False)
    top = src[i0, j0] * (1.0 - wx) + src[i0, j1] * wx
    bottom = src[i1, j0] * (1.0 - wx) + src[i1, j1] * wx
    return top * (1.0 - wy) + bottom * wy


@pytest.fixture(scope="module")
def rng_img():
    return np.random.default_rng(7).random((23, 31, 3))


@pytest.mark.parametrize("method", METHODS)
def test_integer_positions_reproduce_the_samples(method, rng_img):
    yy, xx = np.mgrid[0:23, 0:31]
    out = sample(rng_img, yy, xx, method)
    assert out.dtype == np.float32 and out.shape == rng_img.shape
    if method == "bspline":
        # through the spline coefficients: exact but for float32 rounding
        np.testing.assert_allclose(out, rng_img, rtol=0, atol=1e-6)
    else:
        np.testing.assert_array_equal(out, rng_img.astype(np.float32))


@pytest.mark.parametrize("method", METHODS)
def test_constant_image_stays_constant(method):
    img = np.full((9, 14), 0.37)
    y = np.random.default_rng(1).uniform(-3, 12, (40, 5))
    x = np.random.default_rng(2).uniform(-3, 17, (40, 5))
    np.testing.assert_allclose(sample(img, y, x, method), 0.37, rtol=1e-6)


def test_cubic_methods_reproduce_a_ramp_in_the_interior():
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    ramp = 0.2 + 0.011 * yy - 0.007 * xx
    rng = np.random.default_rng(3)
    # 8 pixels from the edges, where the B-spline no longer sees the edge repeat
    y, x = rng.uniform(8, 31, 500), rng.uniform(8, 41, 500)
    truth = 0.2 + 0.011 * y - 0.007 * x
    for m in ("keys", "bspline"):
        np.testing.assert_allclose(sample(ramp, y, x, m), truth, rtol=0, atol=1e-5, err_msg=m)


def test_lanczos3_is_off_a_ramp_by_its_documented_phase_error():
    # the truncated, normalised sinc does not reproduce ramps: at most
    # 0.020 x the slope, at a fraction of 0.2 pixel, none at 0 and 0.5
    ramp = np.tile(0.01 * np.arange(30.0), (6, 1))
    x = 10.0 + np.array([0.0, 0.2, 0.5, 0.8])
    out = sample(ramp, np.full(4, 3.0), x, "lanczos3")
    err = out - 0.01 * x
    assert abs(err[0]) < 1e-7 and abs(err[2]) < 1e-7
    assert err[1] == pytest.approx(-0.0197 * 0.01, rel=0.02)
    assert err[3] == pytest.approx(+0.0197 * 0.01, rel=0.02)


@pytest.mark.parametrize("shape", [(17, 26), (5, 3), (2, 2), (1, 6)])
def test_bspline_equals_scipy_map_coordinates_nearest(shape):
    rng = np.random.default_rng(4)
    img = rng.random(shape)
    y = rng.uniform(0, shape[0] - 1, 400)
    x = rng.uniform(0, shape[1] - 1, 400)
    ref = ndimage.map_coordinates(img, [y, x], order=3, mode="nearest", prefilter=True)
    np.testing.assert_allclose(sample(img, y, x, "bspline"), ref, rtol=0, atol=1e-5)


def test_bspline_prefilter_in_blocks_equals_one_block(monkeypatch, rng_img):
    from dcdi_core.render import resample
    y = np.random.default_rng(5).uniform(-2, 25, 300)
    x = np.random.default_rng(6).uniform(-2, 33, 300)
    whole = sample(rng_img, y, x, "bspline")
    monkeypatch.setattr(resample, "_FILTER_BYTES", 4096)  # blocks of a few rows, columns
    monkeypatch.setattr(resample, "_CHUNK_BYTES", 4096)   # chunks of a few positions
    np.testing.assert_array_equal(sample(rng_img, y, x, "bspline"), whole)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_linear_equals_the_former_bilinear(dtype, rng_img, monkeypatch):
    from dcdi_core.render import resample
    rng = np.random.default_rng(8)
    y, x = rng.uniform(-4, 27, (60, 70)), rng.uniform(-4, 35, (60, 70))
    img = rng_img.astype(dtype)
    np.testing.assert_array_equal(sample(img, y, x, "linear"), former_bilinear(img, y, x))
    np.testing.assert_array_equal(sample(img[..., 1], y, x, "linear"), former_bilinear(img[..., 1], y, x))
    monkeypatch.setattr(resample, "_CHUNK_BYTES", 10000)  # chunking changes nothing
    np.testing.assert_array_equal(sample(img, y, x, "linear"), former_bilinear(img, y, x))


def test_nearest_never_mixes_values():
    near = (np.arange(8)[:, None] < 4) & (np.arange(12)[None, :] < 6)
    depth = np.where(near, 0.7, 5.0)
    rng = np.random.default_rng(9)
    out = sample(depth, rng.uniform(-1, 9, 500), rng.uniform(-1, 13, 500), "nearest")
    assert set(np.unique(out)) <= {np.float32(0.7), np.float32(5.0)}
    # halves round up, along either axis
    y = np.array([3.0, 3.0, 3.49, 3.5, -7.0])
    x = np.array([5.49, 5.5, 2.0, 2.0, -7.0])
    np.testing.assert_array_equal(sample(depth, y, x, "nearest"), np.float32([0.7, 5.0, 0.7, 5.0, 0.7]))


def test_higher_order_methods_beat_linear_on_the_band_limited_warp():
    rows = {r.method: r for r in warp_accuracy(height=96, width=144, seed=1, timing_shape=None)}
    assert set(rows) == set(METHODS)
    for m in HIGHER:
        assert rows[m].psnr_db > rows["linear"].psnr_db + 3.0, (m, rows[m], rows["linear"])
        assert rows[m].max_abs_error < rows["linear"].max_abs_error
    assert rows["linear"].psnr_db > rows["nearest"].psnr_db
    table = format_warp_accuracy(rows.values())
    assert table.count("\n") == len(METHODS) + 1 and "| bspline |" in table


@pytest.mark.parametrize("method", METHODS)
def test_far_outside_positions_give_edge_values_not_nan(method, rng_img):
    y = np.array([-1e300, 1e300, 5.0, -1e12, 1e6])
    x = np.array([3.0, -1e300, 1e300, -1e12, 1e6])
    out = sample(rng_img, y, x, method)
    assert np.isfinite(out).all()
    corner = sample(rng_img, np.array([22.0]), np.array([30.0]), method)
    np.testing.assert_allclose(out[4], corner[0], rtol=0, atol=1e-7)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_positions_raise_naming_the_argument(bad, rng_img):
    with pytest.raises(InputRangeError, match="^y ="):
        sample(rng_img, np.array([1.0, bad]), np.array([1.0, 2.0]), "keys")
    with pytest.raises(InputRangeError, match="^x ="):
        sample(rng_img, np.array([1.0, 2.0]), np.array([bad, 2.0]), "linear")


def test_bad_arguments_raise(rng_img):
    with pytest.raises(InputRangeError, match="method.*lanczos3"):
        sample(rng_img, np.zeros(2), np.zeros(2), "cubic")
    with pytest.raises(InputRangeError, match="x shape"):
        sample(rng_img, np.zeros(2), np.zeros(3))
    with pytest.raises(InputRangeError, match="img shape"):
        sample(np.zeros(5), np.zeros(2), np.zeros(2))


@pytest.mark.parametrize("method", METHODS)
def test_two_and_three_dimensional_images_and_any_position_shape(method, rng_img):
    rng = np.random.default_rng(10)
    y, x = rng.uniform(0, 22, (4, 5, 6)), rng.uniform(0, 30, (4, 5, 6))
    out3 = sample(rng_img, y, x, method)
    out2 = sample(rng_img[..., 2], y, x, method)
    assert out3.shape == (4, 5, 6, 3) and out2.shape == (4, 5, 6)
    assert out3.dtype == out2.dtype == np.float32
    np.testing.assert_allclose(out3[..., 2], out2, rtol=0, atol=1e-6)
    scalar = sample(rng_img, 3.25, 7.5, method)
    assert scalar.shape == (3,)
    np.testing.assert_allclose(scalar, sample(rng_img, np.array([3.25]), np.array([7.5]), method)[0])


def test_distort_with_keys_and_an_unknown_interpolation():
    lens = load_lens("mos-s1")
    table = radial_distortion(lens)
    g = ImageGeometry.full_sensor(lens, 40, 60)
    yy, xx = np.mgrid[0:40, 0:60]
    img = np.stack([np.sin(0.3 * yy + 0.2 * xx), np.cos(0.25 * xx), 0.5 + 0 * xx], -1) * 0.4 + 0.5
    lin, valid = distort(img, lens, g, distortion=table, return_mask=True)
    keys, valid_k = distort(img, lens, g, distortion=table, return_mask=True, interpolation="keys")
    assert keys.shape == img.shape and keys.dtype == np.float32
    np.testing.assert_array_equal(valid_k, valid)
    assert np.all(keys[~valid] == 0.0)
    assert 0 < np.abs(keys - lin)[valid].max() < 0.1          # a different, close interpolation
    np.testing.assert_array_equal(distort(img, lens, g, distortion=table, interpolation="linear"), lin)
    back = undistort(keys, lens, g, distortion=table, interpolation="bspline")
    assert back.shape == img.shape
    for f in (distort, undistort):
        with pytest.raises(InputRangeError, match="interpolation.*nearest, linear, keys, lanczos3, bspline"):
            f(img, lens, g, distortion=table, interpolation="bicubic")


def test_the_warp_modules_do_not_import_scipy():
    # Blender's Python has numpy but no scipy
    code = ("import sys, dcdi_core.render.resample, lab.resample_accuracy, "
            "dcdi_core.render.distortion; print(sorted(m for m in sys.modules if m.startswith('scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])      # this checkout's dcdi_core
    assert out.stdout.strip() == "[]"
