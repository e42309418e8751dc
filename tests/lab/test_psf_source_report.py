"""`python -m lab report psf-source --quick`: every candidate scored, the files
written, the figures consistent; the scores against a direct computation."""
import json
import math

import numpy as np
import pytest

from lab.cli import main
from lab.psf_source_report import pad_to, point_scores


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("psf-source")
    mp = pytest.MonkeyPatch()
    mp.setenv("DCDI_CACHE_DIR", str(out / "cache"))
    try:
        code = main(["report", "psf-source", "--lens", "mos-s1", "--quick", "--out", str(out)])
    finally:
        mp.undo()
    return code, out


def test_quick_report_scores_every_source(quick_report):
    code, out = quick_report
    assert code == 0
    md = (out / "psf-source.md").read_text()
    for row in ("basis 2", "basis 4 **shipped**", "basis 4 (float32)", "library (16 rays", "trace (default",
                "OLF (shipped)", "PSF map time", "Downstream"):
        assert row in md, row
    assert (out / "psf-source-error-vs-storage.png").stat().st_size > 0
    result = json.loads((out / "psf-source.json").read_text())
    rows = {r["name"]: r for r in result["lenses"][0]["rows"]}
    for r in rows.values():
        assert math.isfinite(r["offgrid"]["psnr_8bit"]) and r["megabytes"] > 0
    # float16 storage changes the served kernels by less than the 8-bit step
    assert abs(rows["basis 4"]["offgrid"]["psnr_8bit"] - rows["basis 4 (float32)"]["offgrid"]["psnr_8bit"]) < 0.2
    assert rows["basis 2"]["megabytes"] < rows["basis 4"]["megabytes"] < rows["basis 4 (float32)"]["megabytes"]
    # a second run reads its references instead of tracing them again
    assert (out / "references-mos-s1.npz").exists()


def test_point_scores_against_a_direct_computation():
    rng = np.random.default_rng(1)
    ref = rng.random((4, 3, 9, 9))
    ref /= ref.sum(axis=(-1, -2), keepdims=True)
    pred = ref + 1e-3 * rng.standard_normal(ref.shape)
    s = point_scores(pred, ref)
    for i in range(4):
        want = []
        for c in range(3):
            a, b = pred[i, c] / pred[i, c].max(), ref[i, c] / ref[i, c].max()
            want.append(-10 * math.log10(np.mean((a - b) ** 2)))
        assert abs(s["psnr_float"][i] - np.mean(want)) < 1e-9
    assert (point_scores(ref, ref)["psnr_8bit"] == 100.0).all()
    # a kernel smaller than the reference is zero-padded: its missing ring counts as error
    small = pad_to(ref, 5)
    assert small.shape[-1] == 5 and np.allclose(small.sum(axis=(-1, -2)), 1.0)
    back = pad_to(small, 9)
    assert back.shape[-1] == 9 and (back[..., 0, :] == 0).all()
