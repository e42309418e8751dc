"""The OLF's training PSFs from a lens's shipped ray map (``PSFDataConfig.
source`` 'raymap'): the grid and the off-grid points are the ray map's own
kernels at those points, a lens without a ray map is traced as before, and
the held-out points are always traced, with their own rays."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.models.olf.data import (PSFDataConfig, _draw_radial_points, build_data, crop_normalise, raymap_points,
                                       trace_points)
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.raymap import RayMapLibrary, open_raymap
from dcdi_core.shipped import raymap_file

SMALL = dict(pupil_samples=16, n_wavelengths=3, n_fields=4, n_depths=3, offgrid=4, held_out=3, kernel_size=31)


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def test_the_grid_and_offgrid_points_are_the_ray_maps_and_held_out_points_are_traced():
    lens_id = "nikkor-85mm-f1-4"
    config = PSFDataConfig(lenses=(lens_id,), source="raymap", held_out_rays=24, **SMALL)
    ls = build_data(config, cache_dir=False).lenses[0]
    lens, rm = load_lens(lens_id), open_raymap(raymap_file(lens_id))
    lib = RayMapLibrary(rm, lens, config.psf_settings(31), config.grid)
    lib.build()
    np.testing.assert_array_equal(ls.grid_y, crop_normalise(lib.psf.reshape(-1, 3, 31, 31)[~lib.zero_energy.ravel()], 31))
    # the held-out points: traced with 24 rays a side, whatever the training's source
    c = ls.val_coords
    want, ok = trace_points(lens, replace(config.psf_settings(31), pupil_samples=24), c["field"], c["depth_m"])
    np.testing.assert_array_equal(ls.val_y, crop_normalise(want[ok], 31))
    # the off-grid training points: the ray map's kernels at those very points
    f, d, _ = _draw_radial_points(np.random.default_rng([config.seed, 0, 1]), config.offgrid, config, False)
    psf, ok = raymap_points(rm, lens, config.psf_settings(31), f, d)
    np.testing.assert_array_equal(ls.off_y, crop_normalise(psf[ok], 31))
    traced = build_data(PSFDataConfig(lenses=(lens_id,), source="trace", held_out_rays=24, **SMALL),
                        cache_dir=False).lenses[0]
    np.testing.assert_array_equal(traced.off_x, ls.off_x)
    np.testing.assert_array_equal(traced.val_y, ls.val_y)


def test_a_lens_without_a_ray_map_is_traced():
    assert raymap_file("mos-s1") is None
    a = build_data(PSFDataConfig(lenses=("mos-s1",), source="raymap", **SMALL), cache_dir=False).lenses[0]
    b = build_data(PSFDataConfig(lenses=("mos-s1",), source="trace", **SMALL), cache_dir=False).lenses[0]
    for name in ("grid_y", "off_y", "val_y"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_the_source_is_checked():
    with pytest.raises(Exception, match="trace or raymap"):
        PSFDataConfig(lenses=("mos-s1",), source="basis")


def test_the_deposit_spread_reaches_every_psf_and_keeps_old_keys():
    """--deposit-sigma: the learned and held-out PSFs' settings carry it; at 0
    (the histogram) a config's settings, hence its points' key, are as before."""
    from dcdi_core.errors import InputRangeError
    plain = PSFDataConfig(lenses=("mos-s1",))
    assert "deposit_sigma_px" not in plain.as_dict() and PSFDataConfig.from_dict(plain.as_dict()) == plain
    smooth = PSFDataConfig(lenses=("mos-s1",), deposit_sigma_px=0.4714)
    assert smooth.psf_settings(31).deposit_sigma_px == 0.4714 and plain.psf_settings(31).deposit_sigma_px == 0.0
    assert PSFDataConfig.from_dict(smooth.as_dict()) == smooth
    for bad in (-0.1, 6.0, float("nan")):
        with pytest.raises(InputRangeError, match="deposit_sigma_px"):
            PSFDataConfig(lenses=("mos-s1",), deposit_sigma_px=bad)


def test_data_too_large_for_the_memory_is_refused_before_any_work(monkeypatch):
    """12 focus bins of a fast lens held 14.6 GB: a run that cannot fit is
    refused by name before a library is made (two such runs side by side were
    ended by the kernel's OOM killer without a word)."""
    import dcdi_core.memory as memory
    from dcdi_core.errors import MemoryLimitError
    from dcdi_core.models.olf import data as olf_data
    monkeypatch.setattr(memory, "available_bytes", lambda: 8 << 30)
    monkeypatch.setattr(olf_data, "_open_libraries", lambda *a, **k: pytest.fail("work started"))
    config = PSFDataConfig(lenses=("nikkor-85mm-f1-4",), focus_lenses=("nikkor-85mm-f1-4",), focus_bins=12,
                           source="raymap")
    with pytest.raises(MemoryLimitError, match=r"13 libraries of 64 fields x 21 depth bins at up to 129 px\) "
                                               r"needs about 13\.\d GiB .* lower --focus-bins"):
        build_data(config, cache_dir=False)
    olf_data._check_memory(PSFDataConfig(lenses=("nikkor-85mm-f1-4",)))      # one library: fits


def test_the_crop_normalises_in_chunks_as_at_once():
    rng = np.random.default_rng(1)
    psf = rng.random((1100, 3, 15, 15)).astype(np.float32)
    psf[7] = 0.0
    got = crop_normalise(psf, 9)
    c = psf[..., 3:12, 3:12].astype(np.float64)
    s = c.sum(axis=(-1, -2), keepdims=True)
    want = np.where(s > 0, c / np.where(s > 0, s, 1.0), 0.0).astype(np.float32)
    assert got.dtype == np.float32 and got.shape == (1100, 3, 9, 9)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(crop_normalise(psf[0], 9), want[0])
