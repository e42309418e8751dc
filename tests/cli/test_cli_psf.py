"""`dcdi psf`, `dcdi psflib`, the lab's `report psf-accuracy`, `dcdi bench psflib`."""
import json

import numpy as np
import pytest

from dcdi_core.cli import main

SMALL = ["--rays", "24", "--wavelengths", "3"]


def _run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_psf_json_npz_png(tmp_path, capsys):
    npz, png = tmp_path / "k.npz", tmp_path / "k.png"
    code, out, _ = _run(capsys, "psf", "mos-s1", "--field", "0.5", "--depth", "2", "--json",
                        "--out", str(npz), "--png", str(png), "--psf-source", "trace", *SMALL)
    assert code == 0
    r = json.loads(out)
    for c in "RGB":
        assert len(r[c]["centroid_mm"]) == 2 and r[c]["rms_radius_mm"] > 0
        assert 0 <= r[c]["energy_outside"] < 0.01
    with np.load(npz) as z:
        assert z["psf"].shape == (3, 41, 41) and z["psf"].dtype == np.float32
        assert float(z["pixel_pitch_mm"]) == pytest.approx(0.0122)
        assert np.allclose(z["psf"].sum(axis=(1, 2)), 1.0, atol=1e-5)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_psf_monochromatic_channels_alike(tmp_path, capsys):
    npz = tmp_path / "m.npz"
    code, _, _ = _run(capsys, "psf", "6p", "--angle", "10", "--depth", "inf", "--wavelength", "550",
                      "--out", str(npz), "--kernel", "21", *SMALL)
    assert code == 0
    with np.load(npz) as z:
        p = z["psf"]
    assert p.shape == (3, 21, 21) and (p[0] == p[1]).all() and (p[1] == p[2]).all()


def test_psf_beyond_image_circle_is_a_clear_error(capsys):
    code, _, err = _run(capsys, "psf", "mos-s1", "--field", "5", "--depth", "2", *SMALL)
    assert code == 2 and "no ray" in err and "--field = 5.0" in err


def test_psflib_build_and_show(tmp_path, capsys):
    lib, png = tmp_path / "lib.npz", tmp_path / "grid.png"
    code, out, err = _run(capsys, "psflib", "build", "mos-s2", "-o", str(lib), "--fields", "3",
                          "--depths", "2", "--no-cache", *SMALL)
    assert code == 0 and lib.exists() and "3 fields" in out
    assert "PSF/s" not in err and "%|" not in err     # no progress bar where stderr is not a terminal
    code, _, _ = _run(capsys, "psflib", "show", str(lib), "--png", str(png))
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_psf_accuracy_report_quick(tmp_path, capsys):
    from lab.cli import main as lab_main
    code = lab_main(["report", "psf-accuracy", "mos-s1", "--quick", "--out", str(tmp_path)])
    assert code == 0
    md = (tmp_path / "psf-accuracy-mos-s1.md").read_text()
    assert "| pupil_samples | 16 |" in md and "depth bins" in md
    assert (tmp_path / "psf-accuracy-mos-s1.png").exists()


@pytest.mark.slow
def test_bench_psflib_quick(capsys):
    code, out, _ = _run(capsys, "bench", "psflib", "--quick")
    assert code == 0 and "where the time goes" in out and "baseline" in out
