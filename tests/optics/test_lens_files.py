"""Lens files: schema validation with errors that name file, surface and field."""
import copy
import math
import tomllib
from pathlib import Path

import pytest
from conftest import PAPER_LENSES, singlet_dict

from dcdi_core.optics.errors import LensFileError, OpticsError
from dcdi_core.optics.lens import Lens, available_lenses, load_lens

LENS_DIR = Path(__file__).resolve().parents[2] / "lenses"


def test_all_paper_lenses_ship_and_load():
    assert set(PAPER_LENSES) <= set(available_lenses())
    for lid in PAPER_LENSES:
        lens = load_lens(lid)
        assert lens.id == lid
        assert sum(s.stop for s in lens.surfaces) == 1
        assert lens.content_hash


def test_paper_tables_transcribed():
    # spot checks against the appendix tables
    s1 = load_lens("mos-s1")
    assert [s.radius_mm for s in s1.surfaces[:3]] == [math.inf, -37.536, -8.711]
    assert s1.surfaces[1].material.name.upper().replace("-", "") == "HK9L"
    dg = load_lens("double-gauss")
    assert len(dg.surfaces) == 11 and dg.stop_index == 5
    assert dg.surfaces[1].thickness_mm == 0.00877
    p6 = load_lens("6p")
    assert len(p6.surfaces) == 13 and p6.surfaces[12].radius_mm == -1185.313


def _bad(mutate):
    d = singlet_dict()
    mutate(d)
    return d


@pytest.mark.parametrize("mutate,pattern", [
    (lambda d: d["surface"][1].update(thickness_mm=-1.0), r"surface 2, field 'thickness_mm'.*out of range"),
    (lambda d: d["surface"][1].update(material="NOPE-GLASS"), r"surface 2, field 'material'.*unknown glass"),
    (lambda d: d["surface"][1].update(material={"nd": 0.5, "vd": 40}), r"surface 2, field 'material'"),
    (lambda d: d["surface"][1].update(semi_diameter_mm=0.0), r"surface 2, field 'semi_diameter_mm'"),
    (lambda d: d["surface"][1].update(radius_mm="big"), r"surface 2, field 'radius_mm'.*number"),
    (lambda d: d["surface"][1].update(raduis_mm=3.0), r"surface 2, field 'raduis_mm'.*unknown key"),
    (lambda d: d["surface"][0].update(stop=False), r"exactly one surface"),
    (lambda d: d["surface"][1].update(stop=True), r"exactly one surface"),
    (lambda d: d.update(schema_version=2), r"schema_version"),
    (lambda d: d.update(id="Bad Id"), r"field 'id'"),
    (lambda d: d.pop("sensor"), r"sensor"),
    (lambda d: d["sensor"].update(resolution_px=[100, 200], pixel_pitch_mm=0.5), r"sensor.semi_diagonal_mm.*1 %"),
    (lambda d: d["surface"][1].update(thickness_mm=math.nan), r"surface 2, field 'thickness_mm'.*finite"),
])
def test_schema_violations_name_surface_and_field(mutate, pattern):
    with pytest.raises(LensFileError, match=pattern):
        Lens.from_dict(_bad(mutate), "my.toml")


def test_error_names_the_file(tmp_path):
    text = (LENS_DIR / "mos-s1.toml").read_text().replace("thickness_mm = 8.5", "thickness_mm = -8.5")
    p = tmp_path / "broken.toml"
    p.write_text(text)
    with pytest.raises(LensFileError) as e:
        load_lens(p)
    assert "broken.toml" in str(e.value) and "surface 2" in str(e.value)


def test_invalid_toml_names_the_file(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text("schema_version = = 1")
    with pytest.raises(LensFileError, match="x.toml.*not valid TOML"):
        load_lens(p)


def test_unknown_lens_id_lists_known_ids():
    with pytest.raises(OpticsError, match="mos-s1"):
        load_lens("no-such-lens")


def _schema_doc_keys() -> dict:
    """{table: keys} of the TOML example in lenses/SCHEMA.md (top level, sensor, stated, surface)."""
    import re
    text = (LENS_DIR / "SCHEMA.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    doc = tomllib.loads(block)
    return {"top": set(doc), "sensor": set(doc["sensor"]), "stated": set(doc["stated"]),
            "surface": set(doc["surface"][0])}


def test_the_schema_doc_lists_exactly_the_keys_the_loader_accepts():
    from dcdi_core.optics import lens as L
    doc = _schema_doc_keys()
    assert doc == {"top": L._TOP_KEYS, "sensor": L._SENSOR_KEYS, "stated": L._STATED_KEYS,
                   "surface": L._SURFACE_KEYS}


def test_shipped_files_use_only_keys_of_the_schema_doc():
    doc = _schema_doc_keys()
    for lid in PAPER_LENSES:
        d = tomllib.loads((LENS_DIR / f"{lid}.toml").read_text())
        assert set(d) <= doc["top"], lid
        assert set(d["sensor"]) <= doc["sensor"], lid
        assert set(d.get("stated", {})) <= doc["stated"], lid
        for i, s in enumerate(d["surface"], 1):
            assert set(s) <= doc["surface"], (lid, i)
        Lens.from_dict(copy.deepcopy(d), lid)


