"""The `dcdi` command as a user calls it."""
import json
import subprocess
import sys

import pytest

from dcdi_core.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_help_explains_units():
    out = subprocess.run([sys.executable, "-m", "dcdi_core", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "metres" in out.stdout and "nm" in out.stdout and "mm" in out.stdout


def test_lens_info_json_keys(capsys):
    code, out, _ = _run(capsys, "lens", "info", "mos-s1", "--json")
    assert code == 0
    info = json.loads(out)
    for key in ("effective_focal_length_mm", "back_focal_length_mm", "f_number",
                "entrance_pupil_position_mm", "entrance_pupil_diameter_mm",
                "in_focus_object_distance_m", "stated"):
        assert key in info
    assert info["stated"]["effective_focal_length_mm"] == 20.0
    assert info["in_focus_object_distance_m"] < 0 and info["in_focus_is_virtual"]
    assert info["wavelength_nm"] == pytest.approx(587.5618)


def test_lens_info_wavelength_changes_focal_length(capsys):
    _, a, _ = _run(capsys, "lens", "info", "mos-s1", "--json", "--paraxial-only", "--wavelength", "450")
    _, b, _ = _run(capsys, "lens", "info", "mos-s1", "--json", "--paraxial-only", "--wavelength", "650")
    assert json.loads(a)["effective_focal_length_mm"] < json.loads(b)["effective_focal_length_mm"]


def test_spot_json(capsys):
    code, out, _ = _run(capsys, "spot", "mos-s1", "--field", "0", "--depth", "inf",
                        "--wavelength", "587.56", "--rays", "32", "--json")
    assert code == 0
    r = json.loads(out)
    assert r["chief_ray_height_mm"] == 0.0
    assert r["centroid_mm"] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert r["rms_radius_mm"] > 0 and r["vignetted_fraction"] == 0.0
    code, out, _ = _run(capsys, "spot", "mos-s1", "--angle", "20", "--depth", "2",
                        "--wavelength", "500", "--json", "--rays", "16")
    r = json.loads(out)
    assert r["angle_deg"] == pytest.approx(20.0) and r["chief_ray_height_mm"] > 5


def test_unknown_lens_is_a_clean_error(capsys):
    code, _, err = _run(capsys, "lens", "info", "nope")
    assert code == 2 and "no lens 'nope'" in err


def test_bad_depth_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit):
        main(["spot", "mos-s1", "--field", "0", "--depth", "-3", "--wavelength", "500"])
    assert "depth must be > 0" in capsys.readouterr().err


def test_lens_import_writes_a_loadable_toml(tmp_path, capsys):
    from support.zemax import singlet_text, write_utf16

    src = tmp_path / "My Singlet.zmx"
    write_utf16(src, singlet_text())
    out = tmp_path / "lenses" / "mine.toml"
    code, stdout, _ = _run(capsys, "lens", "import", str(src), "-o", str(out))
    assert code == 0 and out.exists()
    code, info, _ = _run(capsys, "lens", "info", str(out), "--json", "--paraxial-only")
    assert code == 0 and json.loads(info)["effective_focal_length_mm"] > 0


def test_lens_import_refusal_names_the_line(tmp_path, capsys):
    from support.zemax import singlet_text, write_ascii

    src = tmp_path / "bad.zmx"
    write_ascii(src, singlet_text().replace("TYPE STANDARD", "TYPE TOROIDAL", 1))
    out = tmp_path / "bad.toml"
    code, _, err = _run(capsys, "lens", "import", str(src), "-o", str(out))
    assert code == 2 and "bad.zmx:" in err and "TOROIDAL" in err
    assert not out.exists()


def test_bench_trace_runs_and_reports(capsys):
    code, out, _ = _run(capsys, "bench", "trace", "--rays", "3000", "--repeat", "1")
    assert code == 0
    assert "M ray-surface/s" in out and "baseline" in out and "float32 vs float64" in out
    assert "python build.py bench trace" in out and "--optiland" in out


def test_bench_trace_optiland_spec_is_mos_s1():
    import ast
    from pathlib import Path

    from dcdi_core.bench.trace import optiland_spec
    from dcdi_core.optics.aiming import sources
    from dcdi_core.optics.lens import load_lens

    lens = load_lens("mos-s1")
    aimed = sources(lens, [2.0], field=[0.0, 0.7])
    spec = json.loads(json.dumps(optiland_spec(lens, aimed, 587.5618, 64)))   # what the script reads
    surfs = spec["surfaces"]
    assert len(surfs) == 5 and spec["stop_index"] == 0 and spec["surfaces"][0]["semi_diameter_mm"] == 1.995
    assert [s["index"] for s in surfs] == pytest.approx(lens.refractive_indices([587.5618])[1:, 0].tolist())
    assert surfs[1]["index"] == pytest.approx(1.5168, abs=1e-4) and spec["object_index"] == 1.0
    assert [s["radius_mm"] for s in surfs] == [None, -37.536, -8.711, None, None]
    assert sum(s["thickness_mm"] for s in surfs) == pytest.approx(lens.sensor_z_mm)
    assert spec["object_distance_mm"] == 2000.0 and spec["pupil_samples"] == 64
    # field 0 on axis; field 0.7 below it (its image above), the entrance pupil being the stop at z = 0
    assert spec["field_heights_mm"][0] == 0.0 and spec["field_heights_mm"][1] == pytest.approx(-2000 * aimed.p[1, 0])
    script = Path(__file__).parents[2] / "dcdi_core" / "bench" / "optiland_spot.py"
    tops = {a.name.split(".")[0] for n in ast.walk(ast.parse(script.read_text())) if isinstance(n, ast.Import)
            for a in n.names}
    tops |= {n.module.split(".")[0] for n in ast.walk(ast.parse(script.read_text())) if isinstance(n, ast.ImportFrom)}
    assert tops == {"json", "sys", "time", "numpy", "optiland"}


def test_bench_trace_refuses_a_missing_optiland_interpreter(capsys, tmp_path):
    missing = str(tmp_path / "no-python")
    code, out, err = _run(capsys, "bench", "trace", "--optiland", missing)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "--optiland" in err and missing in err
