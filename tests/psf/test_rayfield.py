"""The Omni-Lens-Field in ray space (dcdi_core.psf.rayfield): a store that
holds a ray map's values as polynomials of (field, 1/depth) serves the map's
kernels where it holds them exactly, its file is checked field by field, and
the source rule serves the paper's lenses from the shipped one at any focus
and stop, close to the trace."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from dcdi_core.errors import ModelError, ModelFileError
from dcdi_core.io.npzfile import read_npz, write_format
from dcdi_core.optics.aperture import Aperture, stopped_down
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf import raymap as R
from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
from dcdi_core.psf.library import LibraryGrid
from dcdi_core.psf.rayfield import FORMAT, FORMAT_VERSION, RayFieldMap, RayFieldOLF, StopBasis, legendre_terms
from dcdi_core.psf.sources import psf_source
from dcdi_core.shipped import olf_rays_file
from tests.psf.test_raymap import LENS, SMALL, psnr        # the small map and the kernels' PSNR of those tests

def node_fit(rm, basis):
    """Legendre coefficients through the map's values at every grid node
    (degrees: nodes - 1, a square system): the store holds them exactly there."""
    f, d = np.meshgrid(rm.fields, rm.diopters, indexing="ij")
    f, d = f.ravel(), d.ravel()
    at = {k: np.asarray(rm.arrays[k], np.float64).transpose(1, 0, *range(2, rm.arrays[k].ndim)).reshape(
        (len(f),) + rm.arrays[k].shape[2:]) for k in ("xy", "chroma", "clip", "chief", "geometry")}
    degrees = (len(rm.fields) - 1, len(rm.diopters) - 1)
    phi = legendre_terms(f, d, float(rm.diopters[0]), degrees)
    return np.linalg.solve(phi, basis.white(at)), degrees


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    lens = load_lens(LENS)
    rm = R.build(lens, SMALL)
    path = tmp_path_factory.mktemp("rayfield") / "small-map.npz"
    rm.save(path)
    rm = R.RayMap.load(path)
    basis = StopBasis.of_map(rm, lens)
    coeffs, degrees = node_fit(rm, basis)
    olf = tmp_path_factory.mktemp("rayfield") / "olf.npz"
    RayFieldOLF.write(olf, [(rm, basis, coeffs, degrees, float(rm.diopters[0]), None)])
    return lens, rm, olf


def _kernels(m, lens, field, depth_m, settings):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        lib = R.RayMapLibrary(m, lens, settings, LibraryGrid(n_fields=2, n_depths=2, near_m=0.7))
        return lib.kernels(field, depth_m)


def test_a_store_of_the_maps_values_at_its_nodes_serves_its_kernels_there(fitted):
    lens, rm, path = fitted
    served = RayFieldOLF.load(path).map_for(LENS)
    s = PSFSettings(kernel_size=45, pixel_pitch_mm=0.02, pupil_samples=96, n_wavelengths=3)
    for field, x in ((0.25, rm.diopters[1]), (0.75, rm.diopters[2]), (1.0, 0.0)):
        depth = np.inf if x == 0 else 1.0 / x
        assert psnr(_kernels(served, lens, field, depth, s), _kernels(rm, lens, field, depth, s)) > 70.0, field
    # refocused and stopped down with blades, between the nodes: the polynomial through the nodes, not the
    # map's cubic pieces, as close to the trace as the map
    shut = stopped_down(lens, Aperture(f_number=5.6, blades=6, rotation_deg=10.0))
    s = PSFSettings(kernel_size=45, pixel_pitch_mm=0.006, pupil_samples=96, n_wavelengths=3, focus_distance_m=1.1)
    got, ref = _kernels(served, shut, 0.6, 1.7, s), _kernels(rm, shut, 0.6, 1.7, s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        traced = psf(shut, depth_m=1.7, field=0.6, settings=s).psf
    assert psnr(got, traced) > psnr(ref, traced) - 3.0 and psnr(got, ref) > 35.0
    # a store whose values are off by 20 um is not the map: the comparison can fail
    c = served.coefficients
    wrong = RayFieldMap.of_fit(rm, served.basis, c + 0.02 * (np.arange(c.size).reshape(c.shape) % 2), served.degrees,
                               served.max_diopters)
    assert psnr(_kernels(wrong, shut, 0.6, 1.7, s), traced) < psnr(ref, traced) - 10.0


def _rewrite(src, dst, edit):
    meta, arrays = read_npz(src, lambda m, field=None, allowed=None: AssertionError(m))
    for k in ("format", "version", "checksum"):
        meta.pop(k)
    edit(meta, arrays)
    write_format(dst, meta, arrays, FORMAT, FORMAT_VERSION)
    return dst


@pytest.mark.parametrize("edit, field", [
    (lambda m, a: m["lenses"][0].update(degrees=[3, 3]), "lenses\\[0\\].legendre"),
    (lambda m, a: m["lenses"][0].update(serve_fields=1), "lenses\\[0\\].serve_fields"),
    (lambda m, a: m["lenses"].append(dict(m["lenses"][0])), "lenses\\[1\\].lens_id"),
    (lambda m, a: m["lenses"][0]["map"]["recipe"].update(n_wavelengths=4), "lenses\\[0\\]"),
    (lambda m, a: a.update(lens0_legendre=a["lens0_legendre"] * 1e9), "lenses\\[0\\].legendre"),
    (lambda m, a: a.pop("lens0_rinv_9_1"), "lenses\\[0\\].rinv_9_1"),
    (lambda m, a: a.update(lens0_ok=np.zeros_like(a["lens0_ok"])), "lenses\\[0\\].ok"),
    (lambda m, a: m["lenses"][0].update(colour="red"), "lenses\\[0\\].colour"),
])
def test_a_damaged_or_edited_file_is_refused_in_one_line_naming_the_field(fitted, tmp_path, edit, field):
    _, _, path = fitted
    bad = _rewrite(path, tmp_path / "bad.npz", edit)
    with pytest.raises(ModelFileError, match=field) as e:
        RayFieldOLF.load(bad)
    assert "\n" not in str(e.value) and str(bad) in str(e.value)
    # --olf FILE reads either kind of OLF file, and refuses this one alike
    from dcdi_core.psf.olf import load_olf_file
    with pytest.raises(ModelFileError, match=field):
        load_olf_file(bad)


def test_a_file_of_another_format_is_refused_naming_both_kinds(fitted, tmp_path):
    _, _, path = fitted
    meta, arrays = read_npz(path, lambda m, field=None, allowed=None: AssertionError(m))
    for k in ("format", "version", "checksum"):
        meta.pop(k)
    write_format(tmp_path / "other.npz", meta, arrays, "dcdi-something", 1)
    from dcdi_core.psf.olf import load_olf_file
    with pytest.raises(ModelFileError, match="format.*dcdi-olf.*dcdi-ray-field"):
        load_olf_file(tmp_path / "other.npz")


def test_a_file_serves_only_the_lenses_it_holds(fitted):
    lens, _, path = fitted
    src = psf_source(lens, olf_file=str(path), pixel_pitch_mm=0.01)
    assert src.kind == "olf" and "in ray space" in src.message and src.plans
    with pytest.raises(ModelError, match="did not learn .*nikkor-24mm-f2.*it learned " + LENS):
        psf_source(load_lens("nikkor-24mm-f2"), olf_file=str(path), source="olf")
    # not its prescription (another lens file under the same id) is not served either
    other = load_lens(LENS)
    other = other.with_surfaces(tuple(s if i else type(s)(**{**s.__dict__, "thickness_mm": s.thickness_mm + 0.1})
                                      for i, s in enumerate(other.surfaces)))
    with pytest.raises(ModelError, match="fingerprint"):
        psf_source(other, olf_file=str(path), source="olf")


@pytest.mark.skipif(olf_rays_file() is None, reason="no OLF in ray space ships")
def test_the_rule_serves_the_papers_lenses_from_the_shipped_store_at_any_focus_and_stop():
    info = json.loads(json.dumps(RayFieldOLF.load(olf_rays_file()).info()))
    assert sorted(e["id"] for e in info["lenses"]) == ["6p", "double-gauss", "mos-s1", "mos-s2"]
    lens = stopped_down(load_lens("6p"), Aperture(f_number=4.0, blades=6))
    s = PSFSettings(kernel_size=41, pixel_pitch_mm=0.003, pupil_samples=192, focus_distance_m=0.9)
    src = psf_source(lens, pixel_pitch_mm=0.003, settings=s, focus_m=0.9, kernel_size=41)
    assert src.kind == "olf" and "in ray space" in src.message and "f/4" in src.message, src.message
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        got = src.library.kernels(0.7, 2.5)
        ref = psf(lens, depth_m=2.5, field=0.7, settings=s).psf
        # the same lens mis-focused by 5 cm: what the comparison tells apart
        off = psf(lens, depth_m=2.5, field=0.7, settings=PSFSettings(**{**s.as_dict(), "focus_distance_m": 0.95})).psf
    assert psnr(got, ref) > 40.0 and psnr(off, ref) < psnr(got, ref) - 6.0
    # an error budget plans its rays as it plans a ray map's
    from dcdi_core.app import PSFRequest
    from dcdi_core.app.render import budgeted
    from dcdi_core.render.geometry import ImageGeometry
    geometry = ImageGeometry.full_sensor(lens, 270, 480)
    request, plan = budgeted(lens, geometry, PSFRequest(max_error_db=35.0))
    assert plan is not None
