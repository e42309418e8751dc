"""The demo's DCDI chain (dcdi_core.demo) on a small synthetic scene: every
picture and the table written, every number finite, bad input refused first."""
import json
import math

import numpy as np
import pytest

from dcdi_core.demo import ChainSettings, run
from dcdi_core.demo.job import verdict
from dcdi_core.errors import DcdiError, InputRangeError

SIZE = (64, 96)


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert run(out, synthetic_size=SIZE, lenses=False, factory_error="no Blender in this test") == 0
    return out


def test_demo_writes_the_strip_the_side_pictures_and_the_table(demo_out):
    from dcdi_core.io.images import read_image
    strip = read_image(demo_out / "dcdi_synthetic.png")
    # capture | corrected | estimated depth | true depth | pipeline DoF | ideal, 4 px gaps
    assert strip.shape == (SIZE[0], 6 * SIZE[1] + 5 * 4, 3)
    panels = [strip[:, i * (SIZE[1] + 4):i * (SIZE[1] + 4) + SIZE[1]] for i in range(6)]
    assert all(p.std() > 0.01 for p in panels)                 # no blank panel
    assert not np.allclose(panels[0], panels[1], atol=1 / 255)  # the correction changed the capture
    for name in ("simulate_mos-s1_synthetic.png", "bokeh_6p_synthetic.png"):
        assert (demo_out / name).stat().st_size > 1000
    report = (demo_out / "report.md").read_text()
    rows = [line for line in report.splitlines() if line.startswith("| synthetic |")]
    assert len(rows) == 2                                       # the estimated depth's and the true depth's
    estimated = next(r for r in rows if len(r.strip("|").split("|")) == 7)
    known = next(r for r in rows if len(r.strip("|").split("|")) == 4)
    cells = [c.strip() for c in estimated.strip("|").split("|")]
    assert all(math.isfinite(float(c)) for c in cells[1:5] + [cells[5].split()[0], cells[6].split()[0]])
    assert all(math.isfinite(float(c)) for c in known.strip("|").split("|")[1:])
    # where the estimated depth's chain is no closer to the ideal than the uncorrected capture's, or `dcdi dof`
    # would refuse its depth, the report says that DCDI needs a depth map and leads with the true depth's chain
    s = json.loads((demo_out / "dcdi_scores.json").read_text())["synthetic"]
    worse = s["dof_psnr"] <= s["dof_uncorrected_psnr"] or bool(s["dof_refuses"])
    assert 0.0 <= s["corrected_share"] <= 1.0
    assert ("DCDI needs a depth map here" in report) == worse
    assert (report.index(known) < report.index(estimated)) == worse
    assert "no factory scene: no Blender in this test" in report
    assert "dcdi_synthetic.png" in report and "Omni-Lens-Field" in report
    assert "## The lenses" not in report                      # lenses=False


def test_demo_scores_are_finite_and_measure_the_chain(demo_out):
    s = json.loads((demo_out / "dcdi_scores.json").read_text())["synthetic"]
    for k in ("capture_psnr", "corrected_psnr", "dof_uncorrected_psnr", "dof_psnr", "depth_abs_rel", "depth_delta1",
              "true_depth_corrected_psnr", "true_depth_dof_psnr", "true_depth_dof_uncorrected_psnr"):
        assert math.isfinite(s[k]), k
    # the capture is aberrated and noisy: far from its sharp truth, not identical to it
    assert 10 < s["capture_psnr"] < 45
    assert 10 < s["dof_psnr"] < 60 and 10 < s["dof_uncorrected_psnr"] < 60
    # the correction kept nowhere (the rule, on this tiny frame) is exactly the uncorrected capture's bokeh
    assert (s["dof_psnr"] == s["dof_uncorrected_psnr"]) == (s["corrected_share"] == 0.0)
    assert s["whole_dof_psnr"] != s["dof_uncorrected_psnr"]
    assert 0 <= s["depth_delta1"] <= 1 and s["depth_abs_rel"] >= 0
    assert {"capture", "correction", "depth", "psfs and bokeh", "references"} <= set(s["seconds"])


def test_demo_refuses_bad_input_before_any_work(tmp_path):
    out = tmp_path / "never"
    with pytest.raises(InputRangeError, match="synthetic scene"):
        run(out, synthetic_size=(4000, 6000), lenses=False)     # larger than the sensor at the learned pitch
    with pytest.raises(DcdiError, match="manifest"):
        run(out, factory_sample=tmp_path / "no-factory-here", lenses=False)
    assert not out.exists()
    with pytest.raises(InputRangeError, match="focus"):
        ChainSettings(focus_m=0)
    with pytest.raises(InputRangeError, match="threads"):
        ChainSettings(threads=0)


def test_verdict_says_plainly_when_no_correction_would_have_served_better():
    class R:
        key = "x"
        scores = {"capture_psnr": 30.0, "corrected_psnr": 29.0, "dof_psnr": 31.0, "dof_uncorrected_psnr": 31.5,
                  "depth_abs_rel": 0.25}
    text = verdict(R())
    assert "lowers" in text and "1.00 dB" in text and "farther from" in text and "served better" in text
    assert "off by 25%" in text
    R.scores = {"capture_psnr": 30.0, "corrected_psnr": 31.0, "dof_psnr": 32.0, "dof_uncorrected_psnr": 31.5,
                "depth_abs_rel": 0.25}
    text = verdict(R())
    assert "raises" in text and "closer to" in text and "served better" not in text
