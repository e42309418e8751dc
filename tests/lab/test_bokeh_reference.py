"""The scatter reference of the lens bokeh (render/bokeh_reference.py): its
vectorised form against a direct per-pixel loop, a single point against its
own PSF, and a crop against the same crop of the full frame."""
import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from lab.bokeh_reference import crop_reference, pixel_kernels, scatter_reference
from dcdi_core.render.geometry import ImageGeometry

# the 9-px kernel clips the far blur (each channel renormalised): the identities hold for any kernel
pytestmark = pytest.mark.filterwarnings("ignore::dcdi_core.psf.compute.KernelTooSmallWarning")


@pytest.fixture(scope="module")
def case():
    """A 6P crop off axis at the lens's own pixel pitch, focused at 1.2 m, with
    depths around it (kernels of a few pixels to the kernel's edge)."""
    lens = load_lens("6p")
    h, w = 14, 17
    pitch = lens.sensor.pixel_pitch_mm
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=(-200.0, -300.0))
    lib = PSFLibrary.open(lens, PSFSettings(kernel_size=9, pupil_samples=12, n_wavelengths=3, pixel_pitch_mm=pitch,
                                            focus_distance_m=1.2), LibraryGrid(n_fields=4, n_depths=3), cache=False)
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    depth = rng.choice([0.8, 1.2, 1.6, 3.0, np.inf, np.nan], (h, w)).astype(np.float32)
    return lib, geom, img, depth


def test_scatter_equals_a_direct_loop_over_pixels(case):
    lib, geom, img, depth = case
    h, w, _ = img.shape
    r = lib.kernel_size // 2
    loop = np.zeros((h + 2 * r, w + 2 * r, 3))
    for y in range(h):
        for x in range(w):
            kern = pixel_kernels(lib, geom, np.array([y]), np.array([x]), np.array([depth[y, x]]))[0]
            loop[y:y + 2 * r + 1, x:x + 2 * r + 1] += np.moveaxis(kern, 0, -1) * img[y, x]
    loop = loop[r:r + h, r:r + w]
    for block in (None, 1, 5):
        out = scatter_reference(img, depth, lib, geom, rows_per_block=block)
        assert out.shape == (h, w, 3) and out.dtype == np.float32
        assert np.abs(out - loop).max() < 1e-5
    assert np.abs(loop - img).max() > 0.05           # the case is blurred at all


def test_a_point_lands_as_its_own_psf_and_invalid_depth_stays_sharp(case):
    lib, geom, _, _ = case
    img = np.zeros((14, 17, 3), np.float32)
    img[7, 8] = [1.0, 2.0, 3.0]
    depth = np.full((14, 17), 3.0, np.float32)
    out = scatter_reference(img, depth, lib, geom)
    kern = pixel_kernels(lib, geom, np.array([7]), np.array([8]), np.array([3.0]))[0]
    r = lib.kernel_size // 2
    np.testing.assert_allclose(out[7 - r:7 + r + 1, 8 - r:8 + r + 1], np.moveaxis(kern, 0, -1) * [1, 2, 3],
                               atol=1e-6)
    assert kern[0, r, r] < 0.9                       # 3 m is out of focus at 1.2 m
    depth[7, 8] = np.nan
    np.testing.assert_array_equal(scatter_reference(img, depth, lib, geom), img)


def test_a_crop_equals_the_same_crop_of_the_full_frame(case):
    lib, geom, img, depth = case
    full = scatter_reference(img, depth, lib, geom)
    np.testing.assert_allclose(crop_reference(img, depth, lib, geom, (5, 10, 6, 12)), full[5:10, 6:12], atol=1e-6)
    with pytest.raises(InputRangeError, match="crop box"):
        crop_reference(img, depth, lib, geom, (5, 20, 6, 12))


def test_gather_form_equals_the_simulation_reports_per_pixel_reference(case):
    # accuracy.per_pixel_reference is an independent gather (its own loop, reflected border):
    # the two agree wherever no tap reaches the border
    from lab.simulation_accuracy import per_pixel_reference
    from lab.bokeh_reference import per_pixel_references
    lib, geom, img, depth = case
    depth = np.where(np.isnan(depth), 2.0, depth)
    scatter, gather = per_pixel_references(img, depth, lib, geom, rows_per_block=3)
    np.testing.assert_array_equal(scatter, scatter_reference(img, depth, lib, geom, rows_per_block=3))
    r = lib.kernel_size // 2
    ref = per_pixel_reference(img, depth, lib, geom)
    inner = (slice(r, -r), slice(r, -r))
    assert np.abs(gather[inner] - ref[inner]).max() < 1e-5
    assert np.abs(gather[inner] - scatter[inner]).max() > 1e-3     # the two forms differ at depth edges
    s_crop, g_crop = crop_reference(img, depth, lib, geom, (5, 9, 6, 11), gather=True)
    np.testing.assert_allclose(g_crop, gather[5:9, 6:11], atol=1e-6)
    np.testing.assert_allclose(s_crop, scatter[5:9, 6:11], atol=1e-6)
