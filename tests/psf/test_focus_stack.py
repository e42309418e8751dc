"""A focus stack (psf.basis): one lens's libraries traced at several focus
distances, one basis for all, served at any focus between them; its file,
its refusals, and its place in the PSF source's choice."""
import json
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.basis import (SHIPPED_FOCUS_RECIPES, BasisFileError, BasisLibrary, BasisRecipe, BasisStore,
                                 compress_stack, shipped_store)
from dcdi_core.psf.library import PSFLibrary
from dcdi_core.psf.sources import psf_source

# mos-s2 (the singlet whose blur changes most with the focus), a tiny grid
TINY = BasisRecipe(rays=24, n_fields=4, n_depths=6, kernel_size=21, rank=400)
FOCUS_D = np.array([0.0, 0.7, 1.4])          # diopters: infinity, 1.43 m, 0.71 m


def _traced(lens, focus_d):
    lib = PSFLibrary(lens, replace(TINY.settings(lens), n_wavelengths=3,
                                   focus_distance_m=math.inf if focus_d == 0 else 1.0 / focus_d), TINY.grid, None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # the 21 px kernel clips the near blur: not what is tested
        lib.build()
    return lib


@pytest.fixture(scope="module")
def stack():
    lens = load_lens("mos-s2")
    libs = [_traced(lens, d) for d in FOCUS_D]
    return lens, libs, compress_stack(libs, FOCUS_D, TINY.rank)


def _psnr(ref, est):
    """Mean PSNR (dB) of kernels each scaled by the reference's peak (the paper's scale)."""
    pk = np.maximum(ref.max(axis=(-1, -2), keepdims=True), 1e-12)
    return float(np.mean(10 * np.log10(1.0 / np.maximum(((ref - est) / pk) ** 2, 1e-20).mean(axis=(-1, -2)))))


def test_a_stored_focus_is_served_as_traced(stack):
    lens, libs, store = stack
    for d, lib in zip(FOCUS_D, libs):
        served = BasisLibrary(store, lens, focus_m=math.inf if d == 0 else 1.0 / d)
        served.build()
        assert _psnr(lib.psf, served.psf) > 60          # full rank: the ripple floor alone
        assert served.settings.focus_distance_m == (math.inf if d == 0 else pytest.approx(1.0 / d))


def test_between_two_focus_distances_the_defocus_is_matched(stack):
    """Halfway between two stored focus distances the kernels are closer to a
    trace there than interpolating the kernels of each depth bin is (the
    shifted depths keep each bin's defocus)."""
    lens, libs, store = stack
    mid = 0.5 * (FOCUS_D[1] + FOCUS_D[2])
    want = _traced(lens, mid).psf
    served = BasisLibrary(store, lens, focus_m=1.0 / mid)
    served.build()
    plain = 0.5 * (libs[1].psf + libs[2].psf)
    assert np.isfinite(served.psf).all() and (served.psf >= 0).all()
    assert np.allclose(served.psf.sum(axis=(-1, -2)), 1.0, atol=1e-5)
    assert _psnr(want, served.psf) > _psnr(want, plain) + 3.0


def test_shifted_depths_outside_the_bins_use_the_other_focus(stack):
    """At infinity's bin the nearer focus's shifted depth lies beyond
    infinity: the farther focus serves it alone."""
    lens, libs, store = stack
    at = store.at_focus(1.0 / (0.25 * FOCUS_D[1]))        # a quarter of the way from infinity
    xb = store.grid.diopters - 0.25 * FOCUS_D[1] + FOCUS_D[1]
    assert np.allclose(at.coeffs[-1], _interp(store.coeffs[1], store.grid.diopters, xb[-1]), atol=1e-6)


def _interp(c, g, x):
    i = np.searchsorted(-g, -x) - 1
    w = (g[i] - x) / (g[i] - g[i + 1])
    return (1 - w) * c[i] + w * c[i + 1]


def test_the_file_round_trip_and_its_refusals(stack, tmp_path):
    lens, _, store = stack
    path = tmp_path / "stack.npz"
    store.save(path)
    back = BasisStore.load(path)
    assert np.allclose(back.focus_diopters, FOCUS_D)
    assert back.coeffs.shape == store.coeffs.shape
    assert back.focus_range_m() == (pytest.approx(1 / 1.4), math.inf)
    with pytest.raises(InputRangeError, match="focus_m"):
        BasisLibrary(back, lens)                                  # a stack needs a focus
    with pytest.raises(InputRangeError, match="0.714 m to inf"):
        back.at_focus(0.5)                                        # nearer than its nearest focus
    for bad in (-1.0, 0.0, float("nan"), "far"):
        assert not back.covers_focus(bad)
    # a file whose focus distances do not increase, or whose coefficients miss one
    z = dict(np.load(path))
    meta = json.loads(str(z.pop("meta")))
    from dcdi_core.io.npzfile import checksum
    for change, field in ((lambda m, a: m.__setitem__("focus_diopters", [0.0, 1.4, 0.7]), "focus_diopters"),
                          (lambda m, a: m.__setitem__("focus_diopters", [0.0, 1.4]), "coeffs")):
        m, a = dict(meta), dict(z)
        change(m, a)
        m.pop("checksum")
        m["checksum"] = checksum(m, a)
        bad = tmp_path / f"bad-{field}.npz"
        np.savez(bad, meta=np.array(json.dumps(m)), **a)
        with pytest.raises(BasisFileError, match=field):
            BasisStore.load(bad)


def test_the_source_serves_a_refocused_lens_from_the_stack(stack, tmp_path, no_ray_olf):
    lens, _, store = stack
    path = tmp_path / "stack.npz"
    store.save(path)
    pitch, settings = store.pixel_pitch_mm, store.settings
    src = psf_source(lens, basis_file=str(path), focus_m=1.2, pixel_pitch_mm=pitch, settings=settings)
    assert src.kind == "basis" and "a focus stack" in src.message and "focus 1.2 m" in src.message, src.message
    # outside its range, or at the prescribed focus: not this file
    src = psf_source(lens, basis_file=str(path), focus_m=0.5, pixel_pitch_mm=pitch, source=None,
                     settings=settings)
    assert src.kind != "basis" and "outside" in src.message
    src = psf_source(lens, basis_file=str(path), pixel_pitch_mm=pitch, settings=settings)
    assert src.kind != "basis" and "focus stack" in src.message


@pytest.mark.parametrize("lens_id", sorted(SHIPPED_FOCUS_RECIPES))
def test_shipped_stacks_serve_their_lens_refocused(lens_id):
    path = shipped_store(lens_id, focus_stack=True)
    assert path is not None, f"no focus stack ships for {lens_id}"
    store = BasisStore.load(path)
    recipe = SHIPPED_FOCUS_RECIPES[lens_id]
    assert np.allclose(store.focus_diopters, recipe.focus_diopters())
    assert store.rank == recipe.rank and store.grid == recipe.grid
    lens = load_lens(lens_id)
    src = psf_source(lens, focus_m=2.0)
    assert src.kind == "basis" and str(path) in src.message
    k = src.library.at(np.array([0.0, 1.0]), np.array([2.0, 0.8]))
    assert np.isfinite(k).all() and np.allclose(k.sum(axis=(-1, -2)), 1.0, atol=1e-4)
