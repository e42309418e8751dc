"""How an image is formed: the kernel against what a sensor records, and
distortion before blur, each against an independent reference."""
import math

import numpy as np
import pytest
from conftest import singlet_dict

from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from lab.simulation_accuracy import blur_then_warp, distortion_case, distorted_reference, psnr
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.simulate import SimulateOptions, LensSimulator, simulate


def pinhole_singlet():
    """A singlet behind a 10 um stop: every ray of a field meets its chief
    ray within 0.1 px of 10 um, at any field (a perfect lens, geometrically)."""
    d = singlet_dict(r1=50.0, back=96.0, sd=10.0)
    d["surface"][0]["semi_diameter_mm"] = 0.005
    d["sensor"]["pixel_pitch_mm"] = 0.01
    return Lens.from_dict(d)


def test_perfect_lens_leaves_an_area_integrated_image_unchanged():
    # the sharp image's pixels are area-integrated already (a render with a
    # box pixel filter, or a sensor): a lens that adds no blur must give it
    # back as it is. The paper's Gaussian deposit (sigma sqrt(2)/3 px) does not.
    lens = pinhole_singlet()
    rng = np.random.default_rng(0)
    img = rng.uniform(0.0, 1.0, (48, 64, 3)).astype(np.float32)
    depth = rng.uniform(0.8, 20.0, (48, 64)).astype(np.float32)
    geom = ImageGeometry.full_sensor(lens, 48, 64)
    grid = LibraryGrid(n_fields=8, n_depths=3)
    settings = PSFSettings(kernel_size=7, pupil_samples=8, wavelength_nm=550.0)
    r = simulate(img, depth, lens, SimulateOptions(geometry=geom, settings=settings, distortion=False))
    assert np.abs(r.image - img).max() < 1e-4
    paper = PSFLibrary.open(lens, PSFSettings(kernel_size=7, pupil_samples=8, wavelength_nm=550.0,
                                              deposit_sigma_px=math.sqrt(2) / 3,
                                              pixel_pitch_mm=geom.pixel_pitch_mm), grid, cache=False)
    blurred = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=False), library=paper)
    assert np.abs(blurred.image - img).max() > 0.05


@pytest.fixture(scope="module")
def distorted_case():
    lens = load_lens("mos-s1")
    h, w = 40, 48
    geom, src, table, scene = distortion_case(lens, h, w, 0.7)
    scene.near, scene.far = 1.5, 8.0          # small blurs: a small kernel holds them
    img, depth = scene.on_grid(src)
    lib = PSFLibrary.open(lens, PSFSettings(kernel_size=25, pupil_samples=24, n_wavelengths=5,
                                            pixel_pitch_mm=geom.pixel_pitch_mm),
                          LibraryGrid(n_fields=24, n_depths=4))
    ref = distorted_reference(scene, lib, geom, table)
    return lens, geom, src, table, img, depth, lib, ref


def test_distorted_simulation_matches_a_per_pixel_reference(distorted_case):
    # each pixel's own PSF at its real image position, applied to the sharp
    # image evaluated exactly where the distortion takes it: warping first
    # and blurring with the real positions' PSFs must reproduce it
    lens, geom, src, table, img, depth, lib, ref = distorted_case
    r = LensSimulator(lens, SimulateOptions(geometry=geom, source_geometry=src), library=lib)(img, depth)
    assert r.info["border"] == "scene"        # the over-scan source feeds the frame's border too
    assert psnr(r.image, ref) > 60.0
    # the former order (PSFs at the pinhole positions, warped afterwards:
    # each blur squeezed by the local stretch, 0.75 here) misses it by far
    old = blur_then_warp(img, depth, lens, lib, geom, src, table)
    assert psnr(old, ref) < 50.0


def test_higher_order_warp_beats_bilinear(distorted_case):
    lens, geom, src, table, img, depth, lib, ref = distorted_case
    got = {m: psnr(LensSimulator(lens, SimulateOptions(geometry=geom, source_geometry=src, interpolation=m),
                                 library=lib)(img, depth).image, ref) for m in ("linear", "keys", "bspline")}
    assert got["keys"] > got["linear"] + 6.0 and got["bspline"] > got["linear"] + 6.0, got


def test_without_over_scan_the_border_is_reflected(distorted_case):
    lens, geom, src, table, img, depth, lib, ref = distorted_case
    crop = LensSimulator(lens, SimulateOptions(geometry=src, distortion=False), library=lib)
    assert crop.margin == 0 and crop(img, depth).info["border"] == "reflected"


def test_no_silent_overrides():
    from dcdi_core.errors import InputRangeError
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.psf.sources import open_library

    lens = load_lens("6p")
    geom = ImageGeometry.full_sensor(lens, 16, 24)
    img = np.full((16, 24, 3), 0.5, np.float32)
    depth = np.full((16, 24), 2.0, np.float32)
    settings = PSFSettings(kernel_size=7, pupil_samples=8, n_wavelengths=3)
    lib = open_library(lens, geom, settings, LibraryGrid(n_fields=4, n_depths=2), cache=False)
    # a library focused as prescribed cannot render a focus at 1.2 m
    with pytest.raises(InputRangeError, match="library's own focus"):
        bokeh(img, depth, lens, BokehOptions(focus_m=1.2, geometry=geom), library=lib)
    bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom), library=lib)
    with pytest.raises(InputRangeError, match="prescribed"):
        bokeh(img, depth, lens, BokehOptions(focus_m="nearby", geometry=geom), library=lib)
    # a PSF pitch that is not the image's
    with pytest.raises(InputRangeError, match="pixel pitch"):
        open_library(lens, geom, PSFSettings(pixel_pitch_mm=0.01), cache=False)
    # the deposit width is part of the cache key
    a = PSFLibrary.open(lens, settings, cache=False)
    b = PSFLibrary.open(lens, PSFSettings(kernel_size=7, pupil_samples=8, n_wavelengths=3, deposit_sigma_px=0.47),
                        cache=False)
    assert a.key != b.key


def test_kernel_rotation_keeps_a_point_and_interpolates_a_smooth_kernel():
    # against the histogram of exactly rotated rays (report simulation-accuracy's table)
    from lab.simulation_accuracy import rotation_rows

    rows = {(q[0], q[1]): q[3:] for q in rotation_rows(quick=True)}
    point, smooth = rows[(0.05, 0.05)], rows[(3.0, 1.5)]
    assert point[1] < 1e-6 and point[3] < 1e-6          # kept: exact at 30 and 45 degrees
    assert point[0] > 0.3 and point[2] > 0.3            # bilinear spread an in-focus point
    assert smooth[1] < 1.05 * smooth[0] + 0.005 and smooth[3] < 1.05 * smooth[2] + 0.005
    assert sum(q[1] + q[3] for q in rows.values()) < sum(q[0] + q[2] for q in rows.values())
