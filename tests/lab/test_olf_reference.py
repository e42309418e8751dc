"""`python -m lab report olf --reference-rays N`: the held-out traces scored
against the same points traced again. With the same rays they are the same
PSFs (100 dB, the cap); with more rays the figure is the traces' own error,
finite, and the ray map's rows come against the new traces."""
from __future__ import annotations

import numpy as np

from dcdi_core.optics.lens import load_lens
from dcdi_core.models.olf.data import trace_points
from dcdi_core.psf.compute import PSFSettings
from lab.olf_report import reference_rows


def _points(lens, settings):
    field, depth = np.array([0.2, 0.8]), np.array([0.9, 3.0])
    y, ok = trace_points(lens, settings, field, depth)
    assert ok.all()
    return {"mos-s1.val.y": y, "mos-s1.val.field": field, "mos-s1.val.depth_m": depth,
            "mos-s1.val.focus_m": np.full(2, np.nan)}


def test_the_references_own_error():
    lens = load_lens("mos-s1")
    settings = PSFSettings(kernel_size=21, pupil_samples=12, n_wavelengths=3, pixel_pitch_mm=0.0122)
    entry = {"psf_settings": settings.as_dict(), "pixel_pitch_mm": settings.pixel_pitch_mm}
    pts = _points(lens, settings)
    same = reference_rows(pts, {"mos-s1": (lens, entry)}, [12])
    assert same[0]["file"] == "the held-out traces against 12-ray traces" and same[0]["psnr_8bit"] == 100.0
    more = reference_rows(pts, {"mos-s1": (lens, entry)}, [24])
    assert more[0]["n"] == 2 and 10.0 < more[0]["psnr_8bit_worst"] < 100.0, more[0]
