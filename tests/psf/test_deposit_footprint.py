"""Kernels converged where they are seen: each ray's energy over its pupil
cell's footprint on the sensor, so that a wide blur's kernel no longer shows
the ray grid beating against the pixel grid, and stops changing as rays are
added."""
import math

import numpy as np
import pytest

from dcdi_core.optics.lens import load_lens
from dcdi_core.psf import compute, deposit
from dcdi_core.psf.compute import PSFSettings

SONNAR = "zeiss-sonnar-50mm-f1-5"
# the stated error: a 120-140 px blur's kernel at the render's ray floor (96 x 96)
# changes by less than this (PSNR against its own peak) when the rays double
CONVERGED_DB = 34.0


def kernel(rays: int, field: float, *, footprint: bool = True, depth_m: float = 10.0) -> np.ndarray:
    """The Sonnar focused at 1.5 m, a light at ``depth_m``, at 8 um pixels: a 138 px disc on the axis."""
    s = PSFSettings(kernel_size=181, pupil_samples=rays, n_wavelengths=5, pixel_pitch_mm=0.008,
                    focus_distance_m=1.5)
    saved = deposit.FOOTPRINT_MIN_PX
    try:
        if not footprint:
            deposit.FOOTPRINT_MIN_PX = math.inf
        with _quiet():
            return compute.psf(load_lens(SONNAR), depth_m=depth_m, field=field, settings=s).psf.astype(np.float64)
    finally:
        deposit.FOOTPRINT_MIN_PX = saved


class _quiet:
    def __enter__(self):
        import warnings
        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore")

    def __exit__(self, *a):
        return self._w.__exit__(*a)


def peak_psnr(ref: np.ndarray, other: np.ndarray) -> float:
    return 10.0 * math.log10(ref.max() ** 2 / np.mean((ref - other) ** 2))


@pytest.fixture(scope="module")
def kernels():
    return {(rays, field, fp): kernel(rays, field, footprint=fp)
            for rays in (96, 192) for field in (0.0, 0.9) for fp in (True, False)}


@pytest.mark.parametrize("field", [0.0, 0.9])
def test_a_wide_kernel_no_longer_changes_when_the_rays_double(kernels, field):
    converged = peak_psnr(kernels[192, field, True], kernels[96, field, True])
    histogram = peak_psnr(kernels[192, field, False], kernels[96, field, False])
    assert converged >= CONVERGED_DB, converged
    # the histogram alone (the deposit before) is the ray grid's moire: 21-26 dB
    assert histogram < CONVERGED_DB - 6.0, histogram


def test_the_footprint_keeps_every_channel_summing_to_one_and_the_disc_flat(kernels):
    k = kernels[96, 0.0, True]
    assert np.allclose(k.sum(axis=(-1, -2)), 1.0, atol=1e-5)
    assert np.isfinite(k).all() and (k >= 0).all()
    # the middle of the defocus disc (a 40 px square in a 138 px disc): evenly lit
    c = k.shape[-1] // 2
    inner = k[1, c - 20:c + 20, c - 20:c + 20]
    flat = inner.std() / inner.mean()
    hist = kernels[96, 0.0, False][1, c - 20:c + 20, c - 20:c + 20]
    # (the Sonnar's spherical aberration shades it a little: 7 %; the histogram's moire: 63 %)
    assert flat < 0.1 and hist.std() / hist.mean() > 0.3, (flat, hist.std() / hist.mean())


def test_a_sharp_kernel_is_the_histogram_exactly():
    """Rays closer than FOOTPRINT_MIN_PX: nothing drawn differently."""
    a = kernel(96, 0.3, depth_m=1.5)
    b = kernel(96, 0.3, depth_m=1.5, footprint=False)
    assert np.array_equal(a, b)


def test_footprint_deposit_conserves_energy_and_survives_degenerate_input():
    rng = np.random.default_rng(0)
    x = rng.uniform(-3, 3, (2, 1, 50))
    y = rng.uniform(-3, 3, (2, 1, 50))
    valid = np.ones(x.shape, bool)
    valid[1] = False                                    # a source with no ray at all
    w = np.ones((1, 3))
    out = deposit.deposit(x, y, valid, w, 15, 5, 0.0, footprint_px=np.array([2.7, np.nan]))
    assert np.isfinite(out).all()
    assert np.allclose(out[0].sum(axis=(-1, -2)), 50.0)
    assert out[1].sum() == 0.0
    # one ray at a pixel centre, a 1-px square: exactly that pixel
    one = deposit.deposit(np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), np.ones((1, 1, 1), bool), w, 5, 5, 0.0,
                          footprint_px=np.array([1.0]))
    assert one[0, 0, 2, 2] == pytest.approx(1.0) and one[0, 0].sum() == pytest.approx(1.0)
    # a 2-px square at a pixel centre: half of the centre pixel's neighbours, a quarter of the corners
    two = deposit.deposit(np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), np.ones((1, 1, 1), bool), w, 5, 5, 0.0,
                          footprint_px=np.array([2.0]))[0, 0]
    assert two[2, 2] == pytest.approx(0.25) and two[2, 1] == pytest.approx(0.125)
    assert two[1, 1] == pytest.approx(0.0625)


def test_a_wide_footprint_is_the_exact_square_within_its_rounding():
    """Sparse rays across a wide blur (a footprint over FOOTPRINT_EXACT_PX):
    the moving sum over the histogram agrees with the exact overlaps where
    the side is a whole odd number of pixels, keeps the energy, and costs a
    pass, not the square's area per ray."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-20, 20, 4000), rng.uniform(-20, 20, 4000)
    wl = np.zeros(4000, np.int64)
    cw = np.ones((1, 3))
    saved = deposit.FOOTPRINT_EXACT_PX
    try:
        deposit.FOOTPRINT_EXACT_PX = 100.0
        exact = deposit._footprint_deposit(x, y, wl, 5.0, 61, cw)
    finally:
        deposit.FOOTPRINT_EXACT_PX = saved
    wide = deposit._footprint_deposit(x, y, wl, 5.0, 61, cw)
    assert wide.sum() == pytest.approx(exact.sum(), rel=1e-9) == pytest.approx(3 * 4000.0)
    # the same square, the rays' sub-pixel positions rounded to their pixel: within a ray's share
    assert np.abs(wide - exact).max() < 0.12 * exact.max()
    assert np.abs(wide - exact).sum() / exact.sum() < 0.05
