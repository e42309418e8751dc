"""The bokeh's per-layer patch choice (render.layer_patch) and the merging of
layers without a depth edge, against the exact path and independent
constructions."""
from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render import layer_patch
from dcdi_core.render.bokeh import BokehOptions, _seams, bokeh
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import psf_map

FAST = PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=21, band_nm=(400.0, 700.0))
EXACT = dict(interp_eps=None, seam_tol=None)


@pytest.fixture(scope="module")
def case():
    lens = load_lens("mos-s1")
    h, w = 192, 256
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122)
    lib = PSFLibrary(lens, replace(FAST, pixel_pitch_mm=geom.pixel_pitch_mm), LibraryGrid(n_fields=8, n_depths=4),
                     None)
    rng = np.random.default_rng(3)
    img = (0.2 + 0.6 * rng.random((h // 8, w // 8, 3))).repeat(8, 0).repeat(8, 1).astype(np.float32)
    depth = np.full((h, w), 6.0)
    depth[60:140, 90:200] = 0.9                                 # a board before a far wall
    return lens, geom, lib, img, depth


def test_wide_patches_keep_a_constant_constant_and_the_kept_range_exact(case):
    lens, geom, lib, _, depth = case
    img = np.full(depth.shape + (3,), 0.37, np.float32)
    # interp_eps 1: every layer takes the cheapest patches (64 px here)
    r = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom, interp_eps=1.0), library=lib)
    assert {c["patch"] for c in r.info["layer_patches"]} == {64}
    assert np.abs(r.image - 0.37).max() < 1e-5
    rng = np.random.default_rng(0)
    tex = rng.random(depth.shape + (3,)).astype(np.float32)
    kept = bokeh(tex, depth, lens, BokehOptions(keep=(0.8, 1.0), geometry=geom, interp_eps=1.0), library=lib)
    # the kept board, beyond the reach of the blurred wall's kernel spill over it: bit for bit
    assert np.array_equal(kept.image[75:125, 105:185], tex[75:125, 105:185])


def test_the_chosen_patches_stay_within_their_bound_of_the_exact_path(case):
    lens, geom, lib, img, depth = case
    exact = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom, **EXACT), library=lib)
    for eps in (0.002, 1.0):
        r = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom, interp_eps=eps, seam_tol=None),
                  library=lib)
        worst = max(c["sampled_rms_error"] or 0.0 for c in r.info["layer_patches"])
        rel = np.sqrt(((r.image - exact.image) ** 2).mean() / (exact.image ** 2).mean())
        # each path lies within its sampled error of the per-pixel kernels: their distance within the sum
        assert rel <= 2 * max(worst, eps if eps < 1 else worst) + 1e-3, (eps, rel, worst)
    assert not np.isnan(r.image).any()


def test_blended_kernel_at_a_patch_centre_is_that_patchs_psf_map_kernel(case):
    _, geom, lib, _, depth = case
    mask = depth < 1.0
    inv = np.where(depth < lib.grid.far_m, 1.0 / depth, 0.0)
    m, b = 32, 8
    d_layer = layer_patch.layer_depth(depth, inv, mask, m, layer_patch.fill_rings(lib.kernel_size, m, b))
    pm = psf_map(lib, geom, d_layer, m)
    # a pixel in the middle of a patch's inner part gets that patch alone; one
    # patch holds the board, one its neighbour beside it (filled from the board)
    for i, j in ((2, 3), (2, 6)):
        y, x = np.array([i * m + m // 2]), np.array([j * m + m // 2])
        got = layer_patch.blended_kernels(lib, geom, inv, mask, y, x, m, b)[0]
        want = pm.kernels[i, j]
        k = min(got.shape[-1], want.shape[-1])
        crop = lambda a: a[:, (a.shape[-1] - k) // 2:(a.shape[-1] + k) // 2, (a.shape[-1] - k) // 2:(a.shape[-1] + k) // 2]
        assert np.abs(crop(got) - crop(want)).sum() / want.sum() < 1e-3
        assert np.abs(crop(got)).sum() >= 0.999 * np.abs(got).sum()


def test_patch_diopters_fill_from_the_nearest_layer_pixels_and_never_nan():
    inv = np.zeros((64, 64))
    mask = np.zeros((64, 64), bool)
    mask[:16, :16] = True
    inv[:16, :16] = 2.0
    mask[48:, 48:] = True
    inv[48:, 48:] = 0.5
    d = layer_patch.patch_diopters(inv, mask, 16, rings=1)
    assert d[0, 0] == 2.0 and d[3, 3] == 0.5
    assert d[0, 1] == 2.0 and d[3, 2] == 0.5                 # a neighbour takes its neighbour's
    assert d[0, 3] == pytest.approx((2.0 * 256 + 0.5 * 256) / 512)   # beyond the rings: the layer's mean
    assert np.isfinite(layer_patch.patch_diopters(inv, np.zeros_like(mask), 16, 1)).all()


def test_seams_list_every_touching_pair_and_its_jumps():
    idx = np.array([[0, 0, 1, -1],
                    [0, 1, 1, 2],
                    [2, 2, 1, 2]])
    inv = np.arange(12, dtype=float).reshape(3, 4)
    got = _seams(idx, inv)
    want = {}
    for y in range(3):
        for x in range(4):
            for dy, dx in ((0, 1), (1, 0)):
                if y + dy < 3 and x + dx < 4:
                    a, b = idx[y, x], idx[y + dy, x + dx]
                    if a >= 0 and b >= 0 and a != b:
                        want.setdefault((min(a, b), max(a, b)), []).append(abs(inv[y, x] - inv[y + dy, x + dx]))
    assert set(got) == set(want)
    for key in want:
        assert sorted(got[key].tolist()) == sorted(want[key])


def test_layers_meet_at_a_depth_edge_stay_apart(case):
    lens, geom, lib, img, _ = case
    h, w = img.shape[:2]
    # a floor (continuous in diopters) and a board standing before a wall: the
    # floor's bands merge, the board and the wall do not
    depth = np.full((h, w), 8.0)
    depth[96:] = 1.0 / np.linspace(1 / 8.0, 1 / 0.8, h - 96)[:, None]
    depth[20:80, 60:180] = 1.1
    r = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom, n_layers=8, interp_eps=None), library=lib)
    apart = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom, n_layers=8, **EXACT), library=lib)
    assert 2 <= r.info["layers"] < apart.info["layers"]
    # the board's edge against the wall is composited as before (its own layer)
    assert np.abs(r.image[20:80, 40:80] - apart.image[20:80, 40:80]).max() < 2e-2
    assert not np.isnan(r.image).any()


@pytest.mark.parametrize("field, value", [("interp_eps", 0.0), ("interp_eps", 1.5), ("interp_eps", True),
                                          ("seam_tol", -0.1), ("seam_tol", "0.2")])
def test_bad_budgets_are_refused_before_any_work(field, value):
    with pytest.raises(InputRangeError, match=field):
        BokehOptions(keep=(1.0, 2.0), **{field: value})
