"""`python -m lab report correction --quick` and `dcdi bench correction --quick`:
they run, write their files, and every score is a finite number in range
(no timing is asserted); the placement of crops on the sensor and the
highlight mask by hand."""
import json
import math

import numpy as np
import pytest

from dcdi_core.cli import main as dcdi
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from lab import correction_report as cr
from lab.cli import main


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("correction")
    code = main(["report", "correction", "--lens", "mos-s1", "--quick", "--out", str(out)])
    return code, out


def _walk(obj, path=""):
    """(path, value) of every number in a nested dict."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, f"{path}/{k}")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path, obj


def test_quick_report_writes_its_files(quick_report):
    code, out = quick_report
    assert code == 0
    for name in ("report.md", "results.json", "correction-mos-s1.jpg"):
        assert (out / name).stat().st_size > 0, name
    text = (out / "report.md").read_text()
    assert "deconvolution, one depth 2 m" in text and "(correction-mos-s1.jpg)" in text


def test_quick_report_scores_are_finite_and_in_range(quick_report):
    _, out = quick_report
    res = json.loads((out / "results.json").read_text())["lenses"]["mos-s1"]
    assert set(res["rows"]) == {cr.SYNTHETIC}
    rows = res["rows"][cr.SYNTHETIC]
    assert set(rows) == {"12.2 um, centre", "12.2 um, mid-field", "12.2 um, edge", cr.CROPS, cr.FULL}
    want = {"capture", "deconvolution, depth per patch", "deconvolution, depth layers 0.1 D",
            "deconvolution, HQS (iterative)",
            "deconvolution, one depth 2 m", "deconvolution, one depth infinity"}
    for case, methods in rows.items():
        assert want <= set(methods), case
        for name, sc in methods.items():
            for view in cr.VIEWS:
                a = sc[view]["all"]
                assert a["pixels"] > 0 and 5.0 < a["psnr"] < 80.0 and 0.0 < a["ssim"] <= 1.0, (case, name, view)
    numbers = list(_walk(res))
    assert numbers and all(math.isfinite(v) for _, v in numbers)
    for label, sc in res["settings"][cr.SYNTHETIC].items():
        assert 5.0 < sc["linear"]["all"]["psnr"] < 80.0, label
        assert sc["seconds_per_megapixel"]["wall"] > 0, label


def test_crops_lie_where_they_are_asked_for():
    lens = load_lens("mos-s1")
    h, w = 320, 480
    centre = cr.crop_geometry(lens, h, w, "centre")
    edge = cr.crop_geometry(lens, h, w, "edge")
    mid = cr.crop_geometry(lens, h, w, "mid-field")
    assert centre.field((h - 1) / 2, (w - 1) / 2) < 0.01
    # the edge crop's outer corner is the sensor's corner pixel: field just under 1
    assert edge.field(h - 1, w - 1) == pytest.approx(math.hypot(1279, 1919) / math.hypot(1280, 1920), abs=1e-3)
    assert mid.field((h - 1) / 2, (w - 1) / 2) == pytest.approx(0.5, abs=0.01)
    with pytest.raises(InputRangeError, match="frame size"):
        cr.crop_geometry(lens, 1300, 480, "centre")


def test_highlight_mask_reaches_the_radius_and_no_further():
    cap = np.zeros((20, 30, 3), np.float32)
    cap[10, 15, 1] = 0.99
    hi = cr.highlights(cap, 3)
    assert hi.sum() == 49 and hi[7:14, 12:19].all()
    assert not cr.highlights(np.full((5, 5, 3), 0.97, np.float32), 3).any()


def test_pooled_sums_score_by_hand():
    s = cr.Sums()
    err = np.array([[0.03, 0.0], [0.0, 0.0]])       # summed over 3 channels: MSE 0.01 on one pixel
    s.add_region(err, np.array([[0.5, np.nan], [1.0, 1.0]]), np.array([[True, True], [False, False]]))
    sc = s.scores()
    assert sc["pixels"] == 2 and sc["psnr"] == pytest.approx(10 * math.log10(1 / 0.005), abs=1e-3)
    assert sc["ssim"] == pytest.approx(0.5)


def test_quick_bench_runs(capsys):
    assert dcdi(["bench", "correction", "--quick"]) == 0
    text = capsys.readouterr().out
    assert "deconvolution:" in text and "goal: deconvolution <= 2 x the simulation" in text


def test_bad_lens_and_folder_are_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["report", "correction", "--lens", "no-such-lens", "--quick", "--out", str(out)]) == 2
    assert main(["report", "correction", "--lens", "mos-s1", "--data", str(tmp_path), "--quick",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no-such-lens" in err and str(tmp_path) in err
    assert not out.exists()
