"""Tests of dcdi_core.optics.materials: catalogue fidelity, lookup rules, model glass."""
import math

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError

from dcdi_core.optics.errors import UnknownGlassError
from dcdi_core.optics.materials import (
    AIR,
    LAMBDA_C_NM,
    LAMBDA_D_NM,
    LAMBDA_F_NM,
    LAMBDA_G_NM,
    Air,
    CatalogueGlass,
    Material,
    ModelGlass,
    catalogue_names,
    get_material,
)

NAMES = catalogue_names()
VISIBLE = np.linspace(400.0, 700.0, 301)
TRACER_BAND = np.linspace(380.0, 780.0, 401)


def _nd_vd_pgf(m):
    n = m.refractive_index(np.array([LAMBDA_D_NM, LAMBDA_F_NM, LAMBDA_C_NM, LAMBDA_G_NM]))
    nd, nf, nc, ng = n
    return nd, (nd - 1.0) / (nf - nc), (ng - nf) / (nf - nc)


def test_required_glasses_present():
    required = {"H-K9L", "LAF2", "PSK3", "SF1", "N-BK7", "N-SF11", "N-SF5", "F2", "SF2", "SF5",
                "SF6", "SF10", "N-SK16", "N-LAK9", "N-BAF10", "N-SF6", "N-F2", "N-K5", "N-SK2",
                "N-LAF2", "F_SILICA"}
    assert required <= set(NAMES)
    assert NAMES == sorted(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_catalogue_nd_vd_reproduced(name):
    g = get_material(name)
    assert isinstance(g, CatalogueGlass)
    nd, vd, _ = _nd_vd_pgf(g)
    # Catalogues print nd to 5 or 6 decimals; the fits reproduce it to a few 1e-6.
    assert abs(nd - g.catalogue_nd) < 2e-5, (name, nd, g.catalogue_nd)
    assert abs(vd - g.catalogue_vd) < 0.1, (name, vd, g.catalogue_vd)
    assert g.nd == pytest.approx(nd, abs=1e-15)
    assert g.vd == pytest.approx(vd, rel=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_catalogue_metadata_documented(name):
    g = get_material(name)
    assert g.source and g.catalogue
    lo, hi = g.wavelength_range_nm
    assert 0 < lo < LAMBDA_G_NM and hi > LAMBDA_C_NM
    assert g.formula in ("sellmeier", "schott") and len(g.coefficients) == 6


@pytest.mark.parametrize("name", NAMES)
def test_normal_dispersion_in_visible(name):
    n = get_material(name).refractive_index(VISIBLE)
    assert np.all(np.isfinite(n))
    assert np.all(np.diff(n) < 0), name


@pytest.mark.parametrize("name", NAMES)
def test_tracer_band_is_finite_even_outside_catalogue_range(name):
    # Several catalogues start above 380 nm (H-ZF52 at 404.7 nm); no error there.
    n = get_material(name).refractive_index(TRACER_BAND)
    assert n.dtype == np.float64 and n.shape == TRACER_BAND.shape
    assert np.all(np.isfinite(n)) and np.all(n > 1.0)


def test_spot_values_against_catalogue_data():
    # Independent spot checks: N-BK7 at 546.074 nm (e line) is 1.51872 in the
    # SCHOTT catalogue; SF1 and N-SF1 share nd but not vd.
    assert float(get_material("N-BK7").refractive_index(546.074)) == pytest.approx(1.51872, abs=1e-5)
    assert get_material("SF1").catalogue_vd == 29.51
    assert get_material("N-SF1").catalogue_vd == 29.62


def test_laf2_is_not_n_laf2():
    laf2, nlaf2 = get_material("LAF2"), get_material("N-LAF2")
    assert laf2 is not nlaf2
    assert laf2.coefficients != nlaf2.coefficients
    assert abs(laf2.vd - nlaf2.vd) > 0.1


def test_h_k9l_close_to_n_bk7_but_distinct():
    hk9l, nbk7 = get_material("H-K9L"), get_material("N-BK7")
    assert hk9l is not nbk7
    diff = np.abs(hk9l.refractive_index(TRACER_BAND) - nbk7.refractive_index(TRACER_BAND))
    assert diff.max() < 5e-5


# --- lookup -------------------------------------------------------------------

@pytest.mark.parametrize("spelling", ["N-BK7", "n-bk7", "NBK7", "nbk7", " N-BK7 "])
def test_lookup_spellings(spelling):
    assert get_material(spelling) is get_material("N-BK7")


@pytest.mark.parametrize("spelling", ["HK9L", "hk9l", "h-k9l"])
def test_lookup_h_k9l(spelling):
    assert get_material(spelling).name == "H-K9L"


@pytest.mark.parametrize("name", NAMES)
def test_hyphenless_alias_maps_to_same_glass(name):
    g = get_material(name)
    assert get_material(name.replace("-", "")) is g
    assert get_material(name.lower()) is g
    assert g.name == name


def test_hyphenless_alias_never_substitutes():
    sf1, nsf1 = get_material("SF1"), get_material("N-SF1")
    assert sf1.name == "SF1" and nsf1.name == "N-SF1"
    assert sf1 is not nsf1
    assert get_material("NSF1") is nsf1
    assert get_material("sf1") is sf1
    # Every name resolves to itself, so no alias shadows another glass.
    assert len({id(get_material(n)) for n in NAMES}) == len(NAMES)


def test_unknown_name_suggests():
    with pytest.raises(UnknownGlassError) as exc:
        get_material("NBK-7")
    assert "N-BK7" in exc.value.suggestions
    assert "N-BK7" in str(exc.value)


@pytest.mark.parametrize("name", ["BK7", "LAF-2", "unobtainium", ""])
def test_unknown_names_raise(name):
    with pytest.raises(UnknownGlassError):
        get_material(name)


def test_bk7_is_not_silently_n_bk7():
    with pytest.raises(UnknownGlassError) as exc:
        get_material("BK7")
    assert exc.value.suggestions[0] == "N-BK7"


def test_unknown_glass_error_is_keyerror():
    with pytest.raises(KeyError):
        get_material("NOSUCHGLASS")


def test_material_instance_returned_as_is():
    m = ModelGlass(1.6, 40.0)
    assert get_material(m) is m
    assert get_material(AIR) is AIR


def test_bad_spec_type():
    with pytest.raises(TypeError):
        get_material(1.5)


# --- air -------------------------------------------------------------------------

@pytest.mark.parametrize("spelling", ["air", "AIR", "Air"])
def test_air(spelling):
    a = get_material(spelling)
    assert a is AIR and isinstance(a, Air) and a.name == "air"
    n = a.refractive_index(TRACER_BAND)
    assert n.dtype == np.float64 and np.all(n == 1.0)
    assert a.nd == 1.0 and math.isinf(a.vd)


# --- vectorisation and wavelength validation --------------------------------------

@pytest.mark.parametrize("spec", ["N-BK7", "H-ZF52A", "air", {"nd": 1.7, "vd": 30.0}])
def test_vectorised_shape(spec):
    m = get_material(spec)
    wl = np.linspace(400.0, 700.0, 12).reshape(3, 4)
    n = m.refractive_index(wl)
    assert isinstance(n, np.ndarray) and n.shape == (3, 4) and n.dtype == np.float64
    flat = np.array([float(m.refractive_index(w)) for w in wl.ravel()])
    np.testing.assert_array_equal(n.ravel(), flat)


def test_scalar_input():
    n = get_material("N-BK7").refractive_index(587.5618)
    assert np.ndim(n) == 0 and float(n) == pytest.approx(1.5168, abs=1e-5)


@pytest.mark.parametrize("bad", [0.0, -500.0, np.nan, np.inf, [500.0, -1.0]])
@pytest.mark.parametrize("spec", ["N-BK7", "air", {"nd": 1.7, "vd": 30.0}])
def test_bad_wavelength_raises(spec, bad):
    with pytest.raises(InputRangeError) as exc:
        get_material(spec).refractive_index(bad)
    assert "wavelength_nm" in str(exc.value)


def test_slightly_outside_catalogue_range_is_allowed():
    g = get_material("H-ZF52")  # catalogue range starts at 404.7 nm
    assert g.wavelength_range_nm[0] > 380.0
    assert np.isfinite(float(g.refractive_index(380.0)))


# --- model glass ------------------------------------------------------------------

MODEL_CASES = [(1.95, 81.6), (1.66, 18.9), (1.5168, 64.17), (1.8, 25.0), (1.45, 90.0)]


@pytest.mark.parametrize("nd,vd", MODEL_CASES)
def test_model_glass_reproduces_nd_vd_exactly(nd, vd):
    m = get_material({"nd": nd, "vd": vd})
    assert isinstance(m, ModelGlass)
    nd_c, vd_c, pgf = _nd_vd_pgf(m)
    assert nd_c == nd
    assert abs(vd_c - vd) < 1e-9
    assert abs(m.vd - vd) < 1e-9 and m.nd == nd


@pytest.mark.parametrize("nd,vd", MODEL_CASES)
def test_model_glass_on_normal_line(nd, vd):
    _, _, pgf = _nd_vd_pgf(ModelGlass(nd, vd))
    assert abs(pgf - (0.6438 - 0.001682 * vd)) < 1e-9


@pytest.mark.parametrize("nd,vd", [(1.95, 81.6), (1.66, 18.9)])
def test_paper_model_glasses(nd, vd):
    m = get_material({"nd": nd, "vd": vd})
    n = m.refractive_index(TRACER_BAND)
    assert np.all(np.isfinite(n))
    assert np.all(np.diff(n) < 0)
    assert np.all(n > 1.0)


def test_model_glass_close_to_real_glass():
    # The normal-line model of N-BK7's (nd, vd) stays within 2e-4 of N-BK7 itself.
    real = get_material("N-BK7")
    model = ModelGlass(real.catalogue_nd, real.catalogue_vd)
    diff = np.abs(model.refractive_index(TRACER_BAND) - real.refractive_index(TRACER_BAND))
    assert diff.max() < 2e-4


def test_model_glass_equality():
    assert ModelGlass(1.6, 40) == ModelGlass(1.6, 40.0)
    assert hash(ModelGlass(1.6, 40)) == hash(ModelGlass(1.6, 40.0))
    assert ModelGlass(1.6, 40) != ModelGlass(1.6, 41)


@pytest.mark.parametrize("spec,field", [
    ({"nd": 0.9, "vd": 50.0}, "nd"),
    ({"nd": 1.0, "vd": 50.0}, "nd"),
    ({"nd": 1.5, "vd": 0.0}, "vd"),
    ({"nd": 1.5, "vd": -3.0}, "vd"),
    ({"nd": float("nan"), "vd": 50.0}, "nd"),
    ({"nd": 1.5, "vd": float("inf")}, "vd"),
    ({"nd": "1.5", "vd": 50.0}, "nd"),
    ({"nd": True, "vd": 50.0}, "nd"),
    ({"nd": 1.5}, "vd"),
    ({"vd": 50.0}, "nd"),
    ({"nd": 1.5, "vd": 50.0, "pgf": 0.55}, "pgf"),
])
def test_bad_model_glass(spec, field):
    with pytest.raises(ValueError) as exc:
        get_material(spec)
    assert isinstance(exc.value, InputRangeError)
    assert field in str(exc.value)


def test_model_glass_nd_below_one_message():
    with pytest.raises(InputRangeError) as exc:
        ModelGlass(0.9, 50.0)
    assert "nd" in str(exc.value) and "> 1" in str(exc.value)


def test_material_is_base():
    for spec in ["air", "N-BK7", {"nd": 1.7, "vd": 30.0}]:
        assert isinstance(get_material(spec), Material)
