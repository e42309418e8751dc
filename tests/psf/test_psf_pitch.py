"""Kernels at another pixel pitch (``psf.pitch``): exact area resampling, and
the Omni-Lens-Field served through it at pitches coarser than the learned one."""
import math

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.psf.pitch import area_resample, overlap_matrix, resampled_size


def _kernels(rng, shape=(2, 3), k=9):
    a = rng.random(shape + (k, k))
    return a / a.sum(axis=(-1, -2), keepdims=True)


def test_area_resampling_keeps_the_sum_and_equals_the_fine_lattice_integral():
    """p0 = 3, p = 5 (units): every pixel edge lies on a half-integer, so the
    piecewise-constant kernel on a unit lattice, summed over 5 x 5 cells, is
    the exact integral over each new pixel."""
    k_old = _kernels(np.random.default_rng(0))
    out = area_resample(k_old, 3.0, 5.0)
    k2 = resampled_size(9, 3.0, 5.0)
    assert out.shape == (2, 3, k2, k2) and k2 == 7            # 9 * 3 / 5 = 5.4 -> 7 (odd, covering)
    fine = np.repeat(np.repeat(k_old, 3, -1), 3, -2) / 9.0     # 27 x 27 unit cells, centred on 0
    pad = (k2 * 5 - 27) // 2
    fine = np.pad(fine, [(0, 0), (0, 0), (pad, pad), (pad, pad)])
    ref = fine.reshape(2, 3, k2, 5, k2, 5).sum(axis=(-1, -3))
    assert np.abs(out - ref).max() < 1e-15
    assert np.abs(out.sum(axis=(-1, -2)) - 1).max() < 1e-12 and out.min() >= 0


def test_area_resampling_of_a_box_is_its_exact_integral():
    # p0 = 1, p = 1.25: new pixel edges at +-0.625, 1.875
    k = np.zeros((3, 3))
    k[1, 1] = 1.0                       # uniform over [-0.5, 0.5]^2: all inside the centre pixel
    out = area_resample(k, 1.0, 1.25)
    assert out.shape == (3, 3) and out[1, 1] == pytest.approx(1.0, abs=1e-15)
    k = np.zeros((3, 3))
    k[1, 2] = 1.0                       # [0.5, 1.5] along x: 0.125 in [-0.625, 0.625], 0.875 beyond
    out = area_resample(k, 1.0, 1.25)
    assert np.allclose(out, [[0, 0, 0], [0, 0.125, 0.875], [0, 0, 0]], atol=1e-15)
    # a 3-pixel box ([-1.5, 1.5]) into p = 2 ([-1, 1] and [1, 3]): 2/3 in the centre, 1/6 either side
    out = area_resample(np.ones((3, 3)) / 9.0, 1.0, 2.0)
    per_axis = np.array([1 / 6, 2 / 3, 1 / 6])
    assert out.shape == (3, 3) and np.allclose(out, np.outer(per_axis, per_axis), atol=1e-15)
    assert np.allclose(overlap_matrix(3, 1.0, 3, 2.0).sum(axis=0), 1.0)     # each old pixel wholly covered


def test_odd_integer_ratio_equals_the_ray_histogram_at_the_coarse_pitch():
    """Pitch ratio 3: every new pixel edge on an old one, so resampling the
    histogram of rays at p0 gives the histogram of the same rays at 3 p0."""
    rng = np.random.default_rng(1)
    y, x = rng.normal(0, 3.0, (2, 20000))                      # ray landing positions, in units of p0
    x, y = np.clip(x, -10.4, 10.4), np.clip(y, -10.4, 10.4)   # inside the 21-px kernel

    def hist(k, p):
        i = np.floor(y / p + k / 2).astype(int)
        j = np.floor(x / p + k / 2).astype(int)
        h = np.zeros((k, k))
        np.add.at(h, (i, j), 1.0 / len(x))
        return h
    coarse = area_resample(hist(21, 1.0), 1.0, 3.0)
    assert coarse.shape == (7, 7) and np.abs(coarse - hist(7, 3.0)).max() < 1e-12


def test_resampling_is_identity_at_the_same_pitch_and_float32_stays_float32():
    k = _kernels(np.random.default_rng(2)).astype(np.float32)
    assert np.array_equal(area_resample(k, 0.0122, 0.0122), k)
    out = area_resample(k, 0.0122, 0.03)
    assert out.dtype == np.float32 and np.abs(out.sum(axis=(-1, -2)) - 1).max() < 1e-6


def test_upsampling_is_refused_with_a_typed_error():
    k = _kernels(np.random.default_rng(3))
    with pytest.raises(InputRangeError, match=r"pixel pitch = 0\.006.*>= 0\.0122 mm.*only downsamples"):
        area_resample(k, 0.0122, 0.006)
    with pytest.raises(InputRangeError, match="pixel pitch"):
        resampled_size(9, 0.0122, 0.01)
    with pytest.raises(InputRangeError, match="odd integer"):
        resampled_size(8, 0.0122, 0.03)
    with pytest.raises(InputRangeError, match="> 0 mm"):
        area_resample(k, 0.0122, -1.0)


# ------------------------------------------------------------------ the shipped OLF through it (numpy only)
@pytest.fixture(scope="module")
def shipped():
    from dcdi_core.psf.sources import SHIPPED
    from dcdi_core.psf.olf import OmniLensField
    if not SHIPPED.exists():
        pytest.skip("no shipped OLF")
    return OmniLensField.load(SHIPPED)


def test_olf_library_at_a_coarser_pitch_serves_resampled_kernels(shipped, no_ray_olf):
    from dcdi_core.psf.sources import OLFLibrary, psf_source
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.psfmap import psf_map
    lens = load_lens("mos-s1")
    p0 = shipped.lens_entry("mos-s1")["pixel_pitch_mm"]
    geom = ImageGeometry.full_sensor(lens, 48, 72)               # 32 x the learned pitch
    lib = OLFLibrary(shipped, lens, pixel_pitch_mm=geom.pixel_pitch_mm)
    assert lib.resampled and lib.pixel_pitch_mm == geom.pixel_pitch_mm
    assert lib.kernel_size == resampled_size(41, p0, geom.pixel_pitch_mm)
    got = lib.kernels([0.2, 0.8], 1.5)
    want = area_resample(shipped.psf(lens, [0.2, 0.8], 1.5), p0, geom.pixel_pitch_mm, lib.kernel_size)
    assert np.allclose(got, want, atol=1e-7) and np.abs(got.sum(axis=(-1, -2)) - 1).max() < 1e-5
    pm = psf_map(lib, geom, np.full((48, 72), 2.0))
    assert pm.kernels.shape[-1] == lib.kernel_size and np.abs(pm.kernels.sum(axis=(-1, -2)) - 1).max() < 1e-5
    src = psf_source(lens, pixel_pitch_mm=geom.pixel_pitch_mm, source="olf")
    assert src.kind == "olf" and "area-resampled" in src.message
    # the default source there: the lens's PSF basis, resampled alike
    src = psf_source(lens, pixel_pitch_mm=geom.pixel_pitch_mm)
    assert src.kind == "basis" and "area-resampled" in src.message
    # the learned pitch (a 1280 x 1920 image on its sensor): served as it is
    full = ImageGeometry.full_sensor(lens, 1280, 1920).pixel_pitch_mm
    assert not OLFLibrary(shipped, lens, pixel_pitch_mm=full).resampled


def test_olf_at_a_finer_pitch_is_traced_and_refused_by_the_library(shipped, no_ray_olf):
    from dcdi_core.psf.sources import OLFLibrary, psf_source
    from dcdi_core.errors import ModelError
    from dcdi_core.optics.lens import load_lens
    lens = load_lens("6p")
    src = psf_source(lens, pixel_pitch_mm=0.006)
    assert src.kind == "trace" and "6 um is finer than the 12.2 um" in src.message
    with pytest.raises(ModelError, match="psf_source olf.*finer") as e:
        psf_source(lens, source="olf", pixel_pitch_mm=0.006)
    assert e.value.in_words({"psf_source": "--psf-source"}).startswith("--psf-source olf")
    with pytest.raises(InputRangeError, match=r"pixel pitch.*learned 6p at 0\.0122 mm.*>= 0\.0122 mm"):
        OLFLibrary(shipped, lens, pixel_pitch_mm=0.006)
    assert math.isfinite(shipped.lens_entry("6p")["pixel_pitch_mm"])
