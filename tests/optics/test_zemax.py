"""Zemax .zmx import (dcdi_core.optics.zemax) and the TOML writer."""
from __future__ import annotations

import math
import tomllib

import pytest

from dcdi_core.optics.errors import ZemaxImportError
from dcdi_core.optics.prescription_toml import dumps_prescription
from dcdi_core.optics.zemax import decode_zmx, read_zmx, write_toml
from support.zemax import (HEADER, MODEL_GLASS, SINGLET_BODY, STOP_SURF, singlet_text,  # noqa: F401
                           write_ascii, write_utf16)


def line_number(text, needle):
    return next(i for i, l in enumerate(text.split("\n"), 1) if needle in l)


# ------------------------------------------------------------------ importing
@pytest.mark.parametrize("writer", [write_ascii, write_utf16], ids=["ascii", "utf16-bom"])
def test_standard_singlet_with_model_glass(tmp_path, writer):
    d = read_zmx(writer(tmp_path / "My Singlet (v2).zmx", singlet_text()))
    assert d["schema_version"] == 1
    assert d["id"] == "my-singlet-v2"
    assert d["name"] == "Test singlet f/5"
    assert d["source"] == "imported from My Singlet (v2).zmx by dcdi lens import"
    assert d["wavelength_nm"] == pytest.approx(587.5618, abs=1e-9)
    assert d["sensor"] == {"semi_diagonal_mm": 21.6}

    s = d["surface"]
    assert len(s) == 3  # object and image are not surfaces
    assert [x["radius_mm"] for x in s] == [math.inf, 1 / 0.02, 1 / -0.005]
    assert [x["thickness_mm"] for x in s] == [2.0, 4.0, 95.5]
    assert [x["semi_diameter_mm"] for x in s] == [5.0, 6.0, 6.2]
    assert [x["material"] for x in s] == ["air", {"nd": 1.5168, "vd": 64.17}, "air"]
    assert [x["stop"] for x in s] == [True, False, False]
    assert s[0]["label"] == 'aperture "stop"'
    assert all("conic" not in x and "aspheric_coefficients" not in x for x in s)


def test_bomless_utf16_and_latin1_are_decoded():
    text = "NAME Ölinse\nUNIT MM\n"
    assert decode_zmx(text.encode("utf-16-le")) == text
    assert decode_zmx(text.encode("latin-1")) == text
    assert decode_zmx(text.encode("utf-8")) == text


def test_even_asphere_with_conic(tmp_path):
    asph = STOP_SURF + """SURF 2
  TYPE EVENASPH
  CURV 0.025 0 0 0 0 ""
  PARM 1 0
  PARM 2 1.0000000000000001e-05
  PARM 3 -2.0000000000000001e-08
  PARM 4 0
  PARM 5 0
  PARM 6 0
  PARM 7 0
  PARM 8 0
  DISZ 3
  GLAS N-BK7 1 0 1.5168 64.17 0 0 0 0 0 0
  CONI -1.2
  DIAM 6 1 0 0 1 ""
"""
    text = HEADER.format(unit="MM") + asph + "SURF 3\n" + SINGLET_BODY.split("SURF 3\n", 1)[1]
    d = read_zmx(write_utf16(tmp_path / "asph.zmx", text))
    s = d["surface"][1]
    assert s["conic"] == -1.2
    assert s["aspheric_coefficients"] == [0.0, 1e-05, -2e-08]
    assert s["radius_mm"] == 1 / 0.025
    assert s["material"] == "N-BK7"


def test_catalogue_glass_name(tmp_path):
    d = read_zmx(write_ascii(tmp_path / "bk7.zmx",
                             singlet_text(glass="N-BK7 1 0 1.5168 64.17 0 0 0 0 0 0")))
    assert d["surface"][1]["material"] == "N-BK7"


def test_six_digit_glass_code(tmp_path):
    d = read_zmx(write_ascii(tmp_path / "code.zmx", singlet_text(glass="517642 0 0 1.5 40")))
    m = d["surface"][1]["material"]
    assert m["nd"] == pytest.approx(1.517) and m["vd"] == pytest.approx(64.2)


def test_inch_units_are_converted(tmp_path):
    d = read_zmx(write_ascii(tmp_path / "inch.zmx", singlet_text(unit="IN")))
    s = d["surface"]
    assert s[1]["radius_mm"] == pytest.approx(25.4 / 0.02)
    assert s[2]["thickness_mm"] == pytest.approx(95.5 * 25.4)
    assert s[0]["semi_diameter_mm"] == pytest.approx(5 * 25.4)
    assert d["sensor"]["semi_diagonal_mm"] == pytest.approx(21.6 * 25.4)


def test_circular_aperture_sets_semi_diameter(tmp_path):
    stop = STOP_SURF.replace('  DIAM 5 1 0 0 1 ""\n', '  DIAM 0 0 0 0 1 ""\n  CLAP 0 4.5 0\n')
    d = read_zmx(write_ascii(tmp_path / "clap.zmx", singlet_text(stop=stop)))
    assert d["surface"][0]["semi_diameter_mm"] == 4.5


# ------------------------------------------------------------------- refusals
def refused(tmp_path, text, needle, *, fragment=None):
    path = write_utf16(tmp_path / "bad.zmx", text)
    with pytest.raises(ZemaxImportError) as ei:
        read_zmx(path)
    e = ei.value
    if needle is not None:
        n = line_number(text, needle)
        assert e.line_number == n
        assert f"bad.zmx:{n}:" in str(e)
        assert needle.strip() in str(e)
    assert "bad.zmx" in str(e)
    if fragment:
        assert fragment in str(e)
    return e


def test_toroidal_surface_is_refused_naming_the_line(tmp_path):
    text = singlet_text().replace("SURF 2\n  TYPE STANDARD", "SURF 2\n  TYPE TOROIDAL")
    refused(tmp_path, text, "TYPE TOROIDAL", fragment="TOROIDAL")


@pytest.mark.parametrize("surface_type", ["COORDBRK", "BINARY_2", "PARAXIAL", "TILTSURF"])
def test_other_surface_types_are_refused(tmp_path, surface_type):
    text = singlet_text().replace("SURF 3\n  TYPE STANDARD", f"SURF 3\n  TYPE {surface_type}")
    refused(tmp_path, text, f"TYPE {surface_type}")


def test_missing_stop_is_refused(tmp_path):
    text = singlet_text(stop=STOP_SURF.replace("  STOP\n", ""))
    e = refused(tmp_path, text, None, fragment="STOP")
    assert e.line_number == 0


@pytest.mark.parametrize("old,new,needle", [
    ("MODE SEQ", "MODE NSC", "MODE NSC"),
    (MODEL_GLASS, "MIRROR 0 0 1.5 40 0 0 0 0 0 0", "GLAS MIRROR"),
    (f"  GLAS {MODEL_GLASS}\n", "  GLAS\n", "  GLAS"),
    ('  DISZ INFINITY\n', '  DISZ INFINITY\n  GLAS N-BK7\n', "GLAS N-BK7"),
    ('  DISZ 4\n', '  DISZ 4\n  SCBD 1 0 0 0 0.5 0 0 0\n', "SCBD"),
    ('  DISZ 4\n', '  DISZ 4\n  OBSC 0 2.5 0\n', "OBSC"),
    ('  DISZ 4\n', '  DISZ -4\n', "DISZ -4"),
    ("UNIT MM", "UNIT FURLONG", "UNIT FURLONG"),
    ('SURF 4\n  TYPE STANDARD\n  CURV 0.0', 'SURF 4\n  TYPE STANDARD\n  CURV 0.01', "CURV 0.01"),
    ('  DIAM 6.2 0 0 0 1 ""\n', '  DIAM 0 0 0 0 1 ""\n', "SURF 3"),
    ('  DIAM 21.6 0 0 0 1 ""\n', '', "SURF 4"),
    (f"GLAS {MODEL_GLASS}", "GLAS ___BLANK 1 0 1.5168 0 0 0 0 0 0 0", "GLAS ___BLANK"),
])
def test_unimportable_constructs_are_refused(tmp_path, old, new, needle):
    text = singlet_text()
    assert old in text
    refused(tmp_path, text.replace(old, new, 1), needle)


def test_zero_tilts_and_ignorable_lines_are_accepted(tmp_path):
    text = singlet_text().replace(
        '  DISZ 4\n', '  DISZ 4\n  SCBD 1 0 0 0 0 0 0 0\n  OBDC 0 0\n  COAT I.50\n  PZUP 0 0 0\n')
    assert len(read_zmx(write_ascii(tmp_path / "ok.zmx", text))["surface"]) == 3


# ---------------------------------------------------------------------- TOML
def test_toml_round_trip_of_imported_prescriptions(tmp_path):
    d1 = read_zmx(write_ascii(tmp_path / "s.zmx", singlet_text()))
    text = singlet_text().replace("SURF 2\n  TYPE STANDARD", "SURF 2\n  TYPE EVENASPH\n"
                                  "  PARM 2 1.2345678901234567e-05\n  PARM 4 -3e-13\n  CONI -0.75")
    d2 = read_zmx(write_ascii(tmp_path / "a.zmx", text))
    assert d2["surface"][1]["aspheric_coefficients"] == [0.0, 1.2345678901234567e-05, 0.0, -3e-13]
    for d in (d1, d2):
        toml = dumps_prescription(d)
        assert tomllib.loads(toml) == d
        assert "radius_mm = inf" in toml
        assert "material = { nd = 1.5168, vd = 64.17 }" in toml
        assert toml.index("[sensor]") < toml.index("[[surface]]")
        assert toml.count("[[surface]]") == 3


def test_dumps_orders_tables_and_escapes_strings():
    d = {
        "surface": [{"radius_mm": -math.inf, "thickness_mm": 0.1 + 0.2, "material": "air",
                     "semi_diameter_mm": 1e-300, "stop": True, "aspheric_coefficients": []}],
        "stated": {"f_number": 2.8, "field_of_view_note": "x"},
        "sensor": {"semi_diagonal_mm": 14.076, "resolution_px": [1280, 1920]},
        "schema_version": 1,
        "id": "t",
        "name": 'quote " backslash \\ tab \t newline \n del \x7f bell \x07 é 漢',
        "wavelength_nm": 587.56,
    }
    text = dumps_prescription(d)
    assert tomllib.loads(text) == d
    lines = text.splitlines()
    assert lines[0] == "schema_version = 1"
    assert text.index("[sensor]") < text.index("[stated]") < text.index("[[surface]]")


def test_write_toml_is_atomic_and_round_trips(tmp_path):
    d = read_zmx(write_ascii(tmp_path / "s.zmx", singlet_text()))
    out = tmp_path / "out" / "s.toml"
    out.parent.mkdir()
    out.write_text("old contents")
    assert write_toml(d, out) == out
    assert tomllib.loads(out.read_text(encoding="utf-8")) == d
    assert [p.name for p in out.parent.iterdir()] == ["s.toml"]  # no temporary left behind


def test_imported_dict_passes_lens_validation(tmp_path):
    lens_mod = pytest.importorskip("dcdi_core.optics.lens")
    d = read_zmx(write_ascii(tmp_path / "s.zmx", singlet_text()))
    lens = lens_mod.Lens.from_dict(tomllib.loads(dumps_prescription(d)))
    assert len(lens.surfaces) == 3 and lens.stop_index == 0
