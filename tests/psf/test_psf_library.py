"""The PSF library: interpolation, laziness, the disk cache."""
import math

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf import library as L
from dcdi_core.psf.compute import PSFSettings, psf
from dcdi_core.psf.library import CacheWarning, LibraryGrid, PSFLibrary

FAST = PSFSettings(pupil_samples=32, n_wavelengths=3)
GRID = LibraryGrid(n_fields=5, n_depths=4)     # bins at 0.7, ~1.0, ~1.9, 10 m and inf


@pytest.fixture
def lens():
    return load_lens("mos-s1")


def test_grid_uniform_in_inverse_depth_plus_infinity():
    g = LibraryGrid(n_fields=64, n_depths=20)
    assert g.fields[0] == 0 and g.fields[-1] == 1 and len(g.fields) == 64
    d = g.diopters
    assert d[-1] == 0 and math.isinf(g.depths_m[-1])
    assert np.allclose(np.diff(d[:-1]), np.diff(d[:-1])[0])
    assert g.depths_m[0] == pytest.approx(0.7) and g.depths_m[-2] == pytest.approx(10.0)


def test_at_grid_points_returns_stored_psf_and_interpolates_linearly(lens):
    lib = PSFLibrary(lens, FAST, GRID, None)
    lib.build()
    d1, d2 = lib.depths_m[1], lib.depths_m[2]
    assert np.array_equal(lib.at(0.25, d1), lib.psf[1, 1])
    mid = 2.0 / (1 / d1 + 1 / d2)                 # half way in inverse depth
    expected = 0.5 * (lib.psf[1, 1] + lib.psf[2, 1])
    assert np.abs(lib.at(0.25, mid) - expected).max() < 1e-6
    expected = 0.5 * (lib.psf[1, 1] + lib.psf[1, 2])
    assert np.abs(lib.at(0.375, d1) - expected).max() < 1e-6


def test_beyond_far_limit_uses_infinity_and_matches_direct_psf(lens):
    lib = PSFLibrary(lens, FAST, GRID, None)
    for d in (10.0, 1e6, 1e10, math.inf):
        assert np.array_equal(lib.at(0.5, d), lib.psf[-1, 2])
    direct = psf(lens, field=0.5, depth_m=math.inf, settings=FAST).psf
    assert np.abs(lib.psf[-1, 2] - direct).max() < 1e-6


def test_near_limit_and_invalid_depths(lens):
    lib = PSFLibrary(lens, FAST, GRID, None)
    with pytest.raises(InputRangeError, match="near limit"):
        lib.at(0.0, 0.5)
    assert np.array_equal(lib.at(0.0, 0.5, clamp_near=True), lib.at(0.0, 0.7))
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(InputRangeError, match="depth_m"):
            lib.at(0.0, bad)
    with pytest.raises(InputRangeError, match="field"):
        lib.at(1.2, 2.0)


def test_lazy_only_the_bins_a_depth_range_needs(lens):
    lib = PSFLibrary(lens, FAST, LibraryGrid(n_fields=3, n_depths=20), None)
    depth_map = np.random.default_rng(1).uniform(2.0, 3.0, size=(40, 60))
    done = lib.ensure(depth_map)
    needed = lib.bins_needed(depth_map)
    assert set(done) == set(needed.tolist())
    assert not lib.computed[0]                 # 0.7 m was not paid for
    assert lib.computed.sum() <= 4
    lo, hi = lib.depths_m[needed.min()], lib.depths_m[needed.max()]
    assert lo <= 2.0 and hi >= 3.0


def test_cache_reused_then_corrupt_file_rebuilt(lens, tmp_path, monkeypatch):
    lib = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    lib.build()
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    # a second open serves from the cache without computing
    def boom(*a, **k):
        raise AssertionError("recomputed although cached")
    monkeypatch.setattr(L, "compute_sources", boom)
    again = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    assert again.computed.all()
    assert np.array_equal(again.psf, lib.psf)
    monkeypatch.undo()
    # corrupt one byte in the middle: detected, warned, rebuilt, never used
    data = bytearray(files[0].read_bytes())
    data[len(data) // 2] ^= 0xFF
    files[0].write_bytes(bytes(data))
    with pytest.warns(CacheWarning, match="unusable"):
        bad = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    assert not bad.computed.any()
    bad.ensure(bins=[0])
    assert np.array_equal(bad.psf[0], lib.psf[0])


def test_truncated_cache_file_is_rebuilt(lens, tmp_path):
    lib = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    lib.ensure(bins=[1])
    f = next(tmp_path.glob("*.npz"))
    f.write_bytes(f.read_bytes()[:100])
    with pytest.warns(CacheWarning):
        again = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    assert not again.computed.any()


def test_changed_lens_or_settings_never_use_a_stale_cache(lens, tmp_path):
    lib = PSFLibrary.open(lens, FAST, GRID, cache_dir=tmp_path)
    lib.ensure(bins=[0])
    from dataclasses import replace
    surfaces = list(lens.surfaces)
    surfaces[1] = replace(surfaces[1], thickness_mm=8.4)
    other = PSFLibrary.open(lens.with_surfaces(surfaces), FAST, GRID, cache_dir=tmp_path)
    assert not other.computed.any() and other.key != lib.key
    finer = PSFLibrary.open(lens, PSFSettings(pupil_samples=48, n_wavelengths=3), GRID, cache_dir=tmp_path)
    assert not finer.computed.any()


def test_save_and_load_round_trip(lens, tmp_path):
    lib = PSFLibrary(lens, FAST, GRID, None)
    lib.ensure(bins=[2, 4])
    p = tmp_path / "lib.npz"
    lib.save(p)
    back = PSFLibrary.load(p)
    assert np.array_equal(back.psf, lib.psf) and back.computed.tolist() == lib.computed.tolist()
    assert back.pixel_pitch_mm == 0.0122 and len(back.wavelengths_nm) == 3
    assert back.meta["response"]["name"]


def test_refocused_library_is_sharp_at_its_focus_distance():
    lens = load_lens("6p")
    st = PSFSettings(pupil_samples=48, n_wavelengths=3, focus_distance_m=2.0)
    near = psf(lens, field=0.0, depth_m=2.0, settings=st)
    far = psf(lens, field=0.0, depth_m=math.inf, settings=st)
    plain = psf(lens, field=0.0, depth_m=2.0, settings=PSFSettings(pupil_samples=48, n_wavelengths=3))
    # paraxial refocus: the 2 m spot shrinks to the lens's spherical-aberration floor
    assert near.rms_radius_mm[1] < plain.rms_radius_mm[1] / 1.5
    assert near.rms_radius_mm[1] < far.rms_radius_mm[1]
