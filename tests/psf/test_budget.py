"""The error budget (psf.budget): the planner's choice from a lens's error
table, its refusals, and the job's result against the converged render."""
import json
import math

import numpy as np
import pytest

from dcdi_core import app
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.aperture import Aperture, stopped_down
from dcdi_core.optics.lens import lens_fingerprint, load_lens
from dcdi_core.psf import budget
from dcdi_core.psf.sources import PSFRequest
from dcdi_core.render.geometry import ImageGeometry

PITCH = 0.08            # mm: the fake table's one measured pitch


def _table(lens, knobs=None):
    stop = lens.surfaces[lens.stop_index].semi_diameter_mm
    knobs = knobs or {"pupil_samples": [[16, 1e-4, 1], [32, 1e-6, 2], [64, 1e-8, 4]],
                      "n_wavelengths": [[3, 1e-4, 1], [9, 1e-6, 2]],
                      "field_step_px": [[16, 1e-6, 1], [64, 1e-4, 1]]}
    return {"format": budget.FORMAT, "version": budget.FORMAT_VERSION, "lens_id": lens.id,
            "lens_fingerprint": lens_fingerprint(lens), "stop_semi_diameter_mm": stop, "scene": "test",
            "source": "raymap", "reference": budget.REFERENCE,
            "sizes": [{"rows": 270, "cols": 480, "pixel_pitch_mm": PITCH, "reference_s": 1.0, "knobs": knobs}]}


@pytest.fixture
def sonnar():
    return load_lens("zeiss-sonnar-50mm-f1-5")


@pytest.fixture
def folder(tmp_path, sonnar):
    (tmp_path / f"{sonnar.id}.json").write_text(json.dumps(_table(sonnar)))
    return tmp_path


def _sum_db(*mse):
    return -10 * math.log10(sum(mse))


def test_the_plan_is_the_cheapest_within_the_budget_and_its_margin(sonnar, folder):
    # 30 dB + 3 dB margin allows 5.0e-4: the coarsest of every knob (3e-4 summed) fits
    p = budget.plan(sonnar, PITCH, 30.0, folder=folder)
    assert p.planned and (p.pupil_samples, p.n_wavelengths, p.field_step_px) == (16, 3, 64)
    assert p.expected_db == pytest.approx(_sum_db(1e-4, 1e-4, 1e-4))
    # 40 dB + 3 allows 5.0e-5: each knob at its 1e-6 level
    p = budget.plan(sonnar, PITCH, 40.0, folder=folder)
    assert (p.pupil_samples, p.n_wavelengths, p.field_step_px) == (32, 9, 16)
    assert p.expected_db >= 40.0 + budget.MARGIN_DB
    # 62 dB + 3 allows 3.2e-7: the wavelengths and fields must be the reference's, the rays 64
    p = budget.plan(sonnar, PITCH, 62.0, folder=folder)
    assert (p.pupil_samples, p.n_wavelengths, p.field_step_px) == (64, 31, None)


def test_the_blur_knobs_are_taken_where_they_save_time_within_the_budget(sonnar, tmp_path):
    """The plan's time: the reference's PSF seconds x the PSF work's
    fraction, plus the blur's seconds at the blur knobs' levels. A coarse
    rule that saves half the blur is taken where its error fits; one
    measured without effect (None) is never offered."""
    knobs = {**_table(sonnar)["sizes"][0]["knobs"],
             "coarse_blur": [[16.0, None, 1.0], [4.0, 1e-6, 0.5], [2.0, 1e-4, 0.25]],
             "support_eps": [[0.01, 1e-6, 0.8]]}
    t = _table(sonnar, knobs)
    t["sizes"][0].update(reference_s=3.0, blur_s=1.0)
    (tmp_path / f"{sonnar.id}.json").write_text(json.dumps(t))
    p = budget.plan(sonnar, PITCH, 30.0, folder=tmp_path)
    assert (p.coarse_blur, p.support_eps) == (2.0, 0.01)
    assert p.seconds == pytest.approx(2.0 * p.cost + 0.25 * 0.8)
    p = budget.plan(sonnar, PITCH, 40.0, folder=tmp_path)      # 1e-4 no longer fits: the next rule
    assert p.coarse_blur == 4.0
    assert all(budget.plan(sonnar, PITCH, b, folder=tmp_path).coarse_blur != 16.0 for b in (25, 30, 40, 50, 60))
    # a simulation fixes them (it has neither): the reference's levels, their error none
    p = budget.plan(sonnar, PITCH, 30.0, {"coarse_blur": None, "support_eps": 1e-3}, folder=tmp_path)
    assert (p.coarse_blur, p.support_eps) == (None, 1e-3)


def test_a_wide_blur_gets_rays_at_most_a_pixel_apart_whatever_the_table_allows(sonnar, folder):
    """A bright light's disc drawn by too few rays shows the pupil grid,
    which a frame's PSNR does not weigh: the rays are at least the widest
    blur's diameter in pixels (budget.RAY_SPACING_PX), up to the reference's."""
    assert budget.min_rays(None) == 1 and budget.min_rays(0.0) == 1
    assert budget.min_rays(40.0) == 40 and budget.min_rays(1e9) == budget.WIDEST_DRAWN_PX
    small = budget.plan(sonnar, PITCH, 30.0, folder=folder, blur_px=10.0)
    assert small.pupil_samples == 16
    wide = budget.plan(sonnar, PITCH, 30.0, folder=folder, blur_px=40.0)
    assert wide.pupil_samples == 64 and "widest blur 40 px" in wide.why
    assert budget.plan(sonnar, PITCH, 30.0, folder=folder, blur_px=500.0).pupil_samples == 96
    # the user's own ray count is kept
    assert budget.plan(sonnar, PITCH, 30.0, {"pupil_samples": 16}, folder=folder, blur_px=500.0).pupil_samples == 16


def test_a_tighter_budget_never_costs_less(sonnar, folder):
    costs = [budget.plan(sonnar, PITCH, b, folder=folder).cost for b in (25, 30, 35, 40, 45, 50, 60, 70)]
    assert costs == sorted(costs)


def test_knobs_the_user_fixed_are_kept_and_their_error_counted(sonnar, folder):
    p = budget.plan(sonnar, PITCH, 40.0, {"pupil_samples": 16}, folder=folder)
    # 16 rays alone cost 1e-4 > 5e-5: nothing meets 40 dB; the plan says so and claims nothing
    assert not p.planned and "cannot keep" in p.why and p.pupil_samples == 16
    # an unmeasured value of a fixed knob: planned, no error claimed
    p = budget.plan(sonnar, PITCH, 30.0, {"n_wavelengths": 7}, folder=folder)
    assert p.planned and p.n_wavelengths == 7 and p.expected_db is None


def test_no_plan_without_a_table_or_at_a_finer_pitch_or_for_another_prescription(sonnar, folder, tmp_path):
    empty = tmp_path / "none"
    empty.mkdir()
    p = budget.plan(sonnar, PITCH, 30.0, folder=empty)
    assert not p.planned and "no error table" in p.why and p.expected_db is None
    # finer than measured: the errors grow with the pitches' ratio squared, up to MAX_EXTRAPOLATION
    near = budget.plan(sonnar, PITCH, 40.0, folder=folder)
    fine = budget.plan(sonnar, PITCH / 2, 40.0, folder=folder)
    assert fine.planned and fine.expected_db == pytest.approx(near.expected_db - 10 * math.log10(4.0))
    p = budget.plan(sonnar, PITCH / (budget.MAX_EXTRAPOLATION * 1.01), 30.0, folder=folder)
    assert not p.planned and "finer" in p.why
    assert budget.plan(sonnar, PITCH * 3, 30.0, folder=folder).planned     # coarser: the table is conservative
    other = load_lens("zeiss-planar-50mm-f1-4")
    (folder / f"{other.id}.json").write_text(json.dumps({**_table(sonnar), "lens_id": other.id}))
    assert "differs" in budget.plan(other, PITCH, 30.0, folder=folder).why


def test_a_stopped_down_lens_shares_the_wide_open_table(sonnar, folder):
    lens = stopped_down(sonnar, Aperture(f_number=4.0, blades=6))
    assert budget.plan(lens, PITCH, 30.0, folder=folder).planned


@pytest.mark.parametrize("damage", [
    lambda t: "{not json",
    lambda t: json.dumps({**t, "sizes": []}),
    lambda t: json.dumps({**t, "version": 99}),
    lambda t: json.dumps({**t, "sizes": [{**t["sizes"][0], "pixel_pitch_mm": -1}]}),
    lambda t: json.dumps({**t, "sizes": [{**t["sizes"][0], "reference_s": float("nan")}]}).replace("NaN", "NaN"),
    lambda t: json.dumps({**t, "sizes": [{**t["sizes"][0], "knobs": {"pupil_samples": [[16, -1e-4, 1]]}}]}),
    lambda t: json.dumps({**t, "sizes": [{**t["sizes"][0], "knobs": {"rays": [[16, 1e-4, 1]]}}]}),
    lambda t: json.dumps({**t, "sizes": [{**t["sizes"][0], "knobs": {"pupil_samples": [[16, 1e-4]]}}]}),
    lambda t: json.dumps({k: v for k, v in t.items() if k != "lens_fingerprint"}),
])
def test_a_damaged_table_is_no_table(sonnar, folder, damage):
    """A table file that cannot be read, or with any field the planner reads
    missing or out of range, is no table: full quality, never a traceback."""
    (folder / f"{sonnar.id}.json").write_text(damage(_table(sonnar)))
    p = budget.plan(sonnar, PITCH, 30.0, folder=folder)
    assert not p.planned and "no error table" in p.why


@pytest.mark.parametrize("bad", [10.0, 100.0, math.nan, math.inf, True, "30"])
def test_a_budget_outside_its_range_is_refused_by_name(bad):
    with pytest.raises(InputRangeError, match="max_error_db"):
        PSFRequest(max_error_db=bad)
    with pytest.raises(InputRangeError, match="fixed"):
        PSFRequest(max_error_db=30.0, fixed=("rays",))


# ---------------------------------------------------------------- the job at its budget, per lens family
def _psnr(a, b):
    return -10 * math.log10(float(np.mean((np.asarray(a, np.float64) - b) ** 2)))


@pytest.mark.parametrize("lens_id, source, focus", [
    ("zeiss-sonnar-50mm-f1-5", "raymap", 1.2),      # a catalogue lens from its ray map, another focus than measured
    ("6p", "trace", 3.0),                            # the paper's phone lens refocused: traced
])
def test_a_planned_bokeh_is_within_its_budget_of_the_converged_render(lens_id, source, focus, tmp_path, monkeypatch):
    from dcdi_core.bench.quality import render
    from dcdi_core.render.synthetic import synthetic_rgbd
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path))
    lens = load_lens(lens_id)
    img, depth = synthetic_rgbd(90, 160, seed=3)
    depth = np.clip(depth, 2.0, 4.5)             # a few depth bins: the converged trace is the test's cost
    ref = render(lens, img, depth, {}, source, focus)[0]
    for b in (30.0, 40.0):
        r = app.bokeh(app.BokehRequest(img, depth, lens, focus_m=focus, psf=PSFRequest(source=source, max_error_db=b),
                                       image_name="the test scene"))
        q = r.info["quality"]
        assert q["budget_db"] == b and q["expected_db"] >= b + budget.MARGIN_DB
        assert _psnr(r.image, ref) >= b, (lens_id, b, q)
    # the plan costs less PSF work than the full-quality defaults
    assert q["relative_cost"] < budget._cost(64, 31, 64)
