"""The ray map: a lens's rays as polynomials of the stop, served for any
focus, f-number, blades and pitch without tracing (dcdi_core.psf.raymap)."""
from __future__ import annotations

import json
import warnings
import zipfile
from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.optics.aperture import Aperture, stopped_down
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf import compute, raymap as R
from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
from dcdi_core.psf.library import LibraryGrid
from dcdi_core.psf.sources import psf_source

LENS = "zeiss-jena-tessar-50mm-f2-8"
SMALL = R.RayMapRecipe(n_fields=5, n_depths=3, near_m=0.6, n_wavelengths=3, degree=9, chroma_degree=5,
                       clip_degree=9, fit_samples=40)


def psnr(a, b) -> float:
    """PSNR (dB) of kernels (3, k, k) each divided by its channel's peak (the paper's scale, float)."""
    a = a / a.max(axis=(-1, -2), keepdims=True)
    b = b / b.max(axis=(-1, -2), keepdims=True)
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    path = tmp_path_factory.mktemp("raymap") / "small.npz"
    R.build(load_lens(LENS), SMALL).save(path)
    return path


def _traced_and_mapped(lens, rm, field, depth_m, settings):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        ref = psf(lens, depth_m=depth_m, field=field, settings=settings).psf
        lib = R.RayMapLibrary(rm, lens, settings, LibraryGrid(n_fields=2, n_depths=2, near_m=0.7))
        return lib.kernels(field, depth_m), ref


def shipped():
    from dcdi_core.shipped import raymap_file
    return R.open_raymap(raymap_file(LENS))


def test_the_map_deposits_the_traced_rays_of_its_grid_points():
    lens, rm = load_lens(LENS), shipped()
    s = PSFSettings(kernel_size=45, pixel_pitch_mm=0.04, pupil_samples=128, n_wavelengths=3)
    for field, depth in ((0.0, np.inf), (0.75, 1.0 / rm.diopters[1])):
        got, ref = _traced_and_mapped(lens, rm, field, depth, s)
        assert psnr(got, ref) > 40.0, (field, depth)


def test_refocused_and_stopped_down_with_blades_it_follows_the_trace():
    lens, rm = load_lens(LENS), shipped()
    stopped = stopped_down(lens, Aperture(f_number=5.6, blades=6, rotation_deg=10.0))
    s = PSFSettings(kernel_size=61, pixel_pitch_mm=0.012, pupil_samples=128, n_wavelengths=3,
                    focus_distance_m=1.2)
    got, ref = _traced_and_mapped(stopped, rm, 0.5, np.inf, s)
    assert psnr(got, ref) > 35.0
    wide, _ = _traced_and_mapped(lens, rm, 0.5, np.inf, s)
    assert psnr(got, wide) < 25.0             # the stop did change the PSF


def test_the_vignetting_of_the_clear_apertures_is_kept(small_map):
    lens, rm = load_lens(LENS), R.RayMap.load(small_map)        # a small map keeps it too
    s = PSFSettings(kernel_size=31, pixel_pitch_mm=0.08, pupil_samples=96, n_wavelengths=3)
    lib = R.RayMapLibrary(rm, lens, s, LibraryGrid(n_fields=3, n_depths=2, near_m=0.7))
    lib.build()
    traced = compute.psf(lens, depth_m=np.inf, field=1.0, settings=s)
    assert traced.vignetted_fraction[1] > 0.05          # the lens does vignette its corner
    assert lib.vignetted_fraction[-1, -1, 1] == pytest.approx(traced.vignetted_fraction[1], abs=0.015)
    assert lib.vignetted_fraction[-1, 0, 1] == pytest.approx(0.0, abs=1e-9)


def test_the_shipped_map_serves_a_catalogue_lens_without_tracing(monkeypatch):
    lens = stopped_down(load_lens(LENS), Aperture(f_number=8.0, blades=5))
    src = psf_source(lens, settings=PSFSettings(focus_distance_m=2.0), pixel_pitch_mm=0.02)
    assert src.kind == "raymap" and "ray map" in src.message and "f/8, 5 blades" in src.message

    def no_trace(*a, **k):
        raise AssertionError("traced")
    monkeypatch.setattr("dcdi_core.psf.library.compute_sources", no_trace)
    src.library.ensure(bins=[0, len(src.library.depths_m) - 1])
    k = src.library.psf[0]
    assert np.isfinite(k).all() and np.allclose(k.sum(axis=(-1, -2)), 1.0, atol=1e-5)


def test_no_map_serves_another_prescription_or_a_wider_stop(small_map):
    rm = R.RayMap.load(small_map)
    with pytest.raises(Exception, match="built for"):
        rm.check_lens(load_lens("zeiss-planar-50mm-f1-4"))
    lens = load_lens(LENS)
    i = lens.stop_index
    wider = lens.with_surfaces(lens.surfaces[:i] + (replace(lens.surfaces[i], semi_diameter_mm=lens.surfaces[
        i].semi_diameter_mm * 1.2),) + lens.surfaces[i + 1:])
    with pytest.raises(Exception):
        rm.check_lens(wider)


def test_a_damaged_or_edited_file_is_refused_in_one_line(small_map, tmp_path):
    bad = tmp_path / "edited.npz"
    with zipfile.ZipFile(small_map) as z:
        members = {n: z.read(n) for n in z.namelist()}
    meta = json.loads(np.load(small_map)["meta"].item())
    meta["recipe"]["degree"] = 4
    with zipfile.ZipFile(bad, "w") as z:
        for n, data in members.items():
            if n != "meta.npy":
                z.writestr(n, data)
        import io
        buf = io.BytesIO()
        np.save(buf, np.array(json.dumps(meta)))
        z.writestr("meta.npy", buf.getvalue())
    with pytest.raises(R.RayMapFileError) as e:
        R.RayMap.load(bad)
    assert "\n" not in str(e.value) and str(bad) in str(e.value)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(R.RayMapFileError):
        R.RayMap.load(tmp_path / "junk.npz")


def test_interpolation_weights_are_exact_at_nodes_and_sum_to_one():
    idx, w = R.grid_weights(np.array([0.0, 2.0, 2.4, 6.9, 7.0]), 8)
    assert np.allclose(w.sum(1), 1.0)
    assert w[1, list(idx[1]).index(2)] == pytest.approx(1.0)
    a = R._wavelength_weights(np.array([400.0, 437.5, 550.0, 700.0]), np.linspace(400, 700, 5))
    assert np.allclose(a.sum(1), 1.0) and a[2, 2] == pytest.approx(1.0)


def test_a_source_opens_its_psfs_at_a_jobs_geometry_from_one_ray_map(monkeypatch):
    """``PSFSource.at`` and ``PSFLibrary.at_geometry`` make a ray map's PSFs
    at another pitch from the same map (never traced), and a renderer given
    no library takes the ray map where one ships (``lens_library``)."""
    from dcdi_core.psf.raymap import RayMapLibrary
    from dcdi_core.psf.sources import PSFRequest, lens_library
    from dcdi_core.render.geometry import ImageGeometry

    def no_trace(*a, **k):
        raise AssertionError("traced")
    monkeypatch.setattr("dcdi_core.psf.library.compute_sources", no_trace)
    lens = load_lens(LENS)
    geom = ImageGeometry.full_sensor(lens, 60, 90)
    req = PSFRequest(settings=PSFSettings(focus_distance_m=2.0, pupil_samples=16, n_wavelengths=5))
    src = psf_source(lens, settings=req.settings, pixel_pitch_mm=geom.pixel_pitch_mm)
    lib = src.at(geom, req).library
    assert isinstance(lib, RayMapLibrary) and lib.raymap is src.library.raymap
    assert lib is src.library and src.at(geom, req).library is lib      # one library, its bins made once
    other = src.at(geom, replace(req, settings=replace(req.settings, pupil_samples=12))).library
    assert other is not lib and other.settings.pupil_samples == 12
    coarse_geom = ImageGeometry.full_sensor(lens, 30, 45)
    coarse = lib.at_geometry(coarse_geom)
    assert isinstance(coarse, RayMapLibrary) and coarse.raymap is lib.raymap
    assert coarse.pixel_pitch_mm == pytest.approx(2 * lib.pixel_pitch_mm, rel=1e-3)
    assert coarse.settings.pupil_samples == 16 and coarse.settings.focus_distance_m == 2.0
    coarse.ensure(bins=[0])
    assert np.allclose(coarse.psf[0].sum(axis=(-1, -2)), 1.0, atol=1e-5)
    own = lens_library(lens, geom, req.settings)
    assert isinstance(own, RayMapLibrary)


def test_a_renderer_given_no_library_traces_a_lens_without_a_ray_map():
    from dcdi_core.psf.raymap import RayMapLibrary
    from dcdi_core.psf.sources import lens_library
    from dcdi_core.render.geometry import ImageGeometry
    lens = load_lens("mos-s1")
    lib = lens_library(lens, ImageGeometry.full_sensor(lens, 60, 90), PSFSettings(pupil_samples=8, n_wavelengths=3),
                       cache=False)
    assert type(lib).__name__ == "PSFLibrary" and not isinstance(lib, RayMapLibrary)


def test_a_precise_map_keeps_its_fits_in_float64_and_serves_as_a_stored_one(small_map, tmp_path):
    """``build(precise=True)`` (a study's training data) holds the very fits
    a shipped map rounds (float32 landing points, float16 chromatic terms),
    and is read and served by the same code."""
    lens = load_lens(LENS)
    stored = R.RayMap.load(small_map)
    precise = R.build(lens, SMALL, precise=True)
    assert {precise.arrays[k].dtype for k in ("xy", "chroma", "clip")} == {np.dtype(np.float64)}
    assert stored.arrays["chroma"].dtype == np.float16
    for k in ("xy", "chroma", "clip"):
        np.testing.assert_array_equal(precise.arrays[k].astype(stored.arrays[k].dtype), stored.arrays[k])
    rounding = np.abs(precise.arrays["chroma"] - stored.arrays["chroma"].astype(np.float64)).max()
    assert rounding > 0.0            # the float16 rounding it removes
    precise.save(tmp_path / "precise.npz")
    again = R.RayMap.load(tmp_path / "precise.npz")
    s = PSFSettings(kernel_size=31, pixel_pitch_mm=0.02, pupil_samples=48, n_wavelengths=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        a = R.RayMapLibrary(again, lens, s, LibraryGrid(n_fields=2, n_depths=2, near_m=0.7)).kernels(0.5, 1.5)
        b = R.RayMapLibrary(stored, lens, s, LibraryGrid(n_fields=2, n_depths=2, near_m=0.7)).kernels(0.5, 1.5)
    assert psnr(a, b) > 50.0
