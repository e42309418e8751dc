"""The PSF sampling an image needs: fields a step in pixels apart, focus
rounded within a blur tolerance (psf.sampling), and the jobs that use them."""
import math

import numpy as np
import pytest

from dcdi_core import app
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import Lens
from dcdi_core.psf import sampling
from dcdi_core.psf.library import LibraryGrid
from dcdi_core.psf.sources import PSFRequest
from dcdi_core.render.request import RenderRequest


@pytest.fixture(scope="module")
def lens():
    return Lens.from_toml(_path("6p"))


def _path(lens_id):
    from dcdi_core.optics.lens import lens_dirs
    return next(str(d / f"{lens_id}.toml") for d in lens_dirs() if (d / f"{lens_id}.toml").exists())


def test_fields_follow_the_image_pitch_and_never_exceed_the_source_grid():
    grid = LibraryGrid()
    # 1000 px from the axis to the corner, 16 px apart: 64 fields (capped at the grid's)
    assert sampling.field_grid(grid, 10.0, 0.01, 16.0) is grid
    coarse = sampling.field_grid(grid, 10.0, 0.04, 16.0)          # 250 px: 17 fields
    assert coarse.n_fields == 17 and coarse.n_depths == grid.n_depths and coarse.near_m == grid.near_m
    assert sampling.field_grid(grid, 10.0, 1.0, 16.0).n_fields == sampling.MIN_FIELDS
    assert sampling.field_grid(None, 10.0, 0.04, None) is None
    assert sampling.field_grid(grid, 10.0, 0.04, None) is grid
    # neighbouring fields at most the step apart, in pixels
    assert 250.0 / (coarse.n_fields - 1) <= 16.0


@pytest.mark.parametrize("bad", [0, -1.0, math.nan, math.inf])
def test_bad_steps_are_refused(bad):
    with pytest.raises(InputRangeError):
        sampling.field_grid(LibraryGrid(), 10.0, 0.04, bad)
    with pytest.raises(InputRangeError):
        PSFRequest(field_step_px=bad)
    with pytest.raises(InputRangeError):
        PSFRequest(focus_tolerance_px=bad)


def test_rounded_focus_stays_within_the_blur_tolerance(lens):
    pitch = 0.02
    per_diopter = sampling.blur_px_per_diopter(lens, pitch)
    # the thin lens: entrance pupil x focal length per diopter, in pixels
    from dcdi_core.optics import paraxial
    fo = paraxial.first_order(lens)
    efl = fo.effective_focal_length_mm
    assert per_diopter == pytest.approx(efl / fo.f_number * efl / 1000.0 / pitch, rel=1e-9)
    rng = np.random.default_rng(0)
    for tol in (0.1, 0.25, 1.0):
        for f in np.concatenate([rng.uniform(0.7, 20.0, 50), [0.7, 1.0, 3.0, math.inf]]):
            g = sampling.snap_focus(lens, f, pitch, tol)
            moved_px = abs(1.0 / f - 1.0 / g) * per_diopter
            assert moved_px <= tol * (1 + 1e-9)
            assert g >= f                                   # never nearer than asked: a range ending at inf holds it
            assert sampling.snap_focus(lens, g, pitch, tol) == pytest.approx(g, rel=1e-12)   # on the grid: put
    assert sampling.snap_focus(lens, 2.0, pitch, None) == 2.0
    assert sampling.snap_focus(lens, None, pitch, 0.25) is None
    assert sampling.snap_focus(lens, "prescribed", pitch, 0.25) == "prescribed"


def _scene(h=90, w=160):
    y, x = np.mgrid[0:h, 0:w]
    img = ((0.1 + 0.8 * ((x // 5 + y // 5) % 2))[..., None] * np.array([1.0, 0.7, 0.4])).astype(np.float32)
    depth = (0.8 + 6.0 * (x / w) ** 2).astype(np.float32)
    return img, depth


def test_a_bokeh_with_fewer_fields_and_a_rounded_focus_stays_close_and_shares_psfs(lens):
    img, depth = _scene()
    cache = app.SourceCache(4)

    def run(focus, **kw):
        req = app.BokehRequest(img, depth, lens, focus_m=focus, render=RenderRequest(lens, patch=16),
                               psf=PSFRequest(**kw), image_name="x")
        return app.bokeh(req, None, cache=cache)

    exact = run(1.5)
    coarse = run(1.5, field_step_px=16.0)
    assert coarse.source.library.grid.n_fields < exact.source.library.grid.n_fields
    assert 10 * np.log10(1.0 / np.mean((coarse.image - exact.image) ** 2)) > 40.0
    a = run(1.5, field_step_px=16.0, focus_tolerance_px=0.25)
    b = run(1.502, field_step_px=16.0, focus_tolerance_px=0.25)
    assert a.info["focus_used_m"] == b.info["focus_used_m"]
    assert a.source.library is b.source.library                 # the second focus paid no PSFs
    assert np.isfinite(a.image).all()
    assert 10 * np.log10(1.0 / np.mean((a.image - coarse.image) ** 2)) > 35.0


def test_bench_sampling_quick_prints_each_way(capsys):
    from dcdi_core.cli import main
    assert main(["bench", "sampling", "--quick"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 6p |")]
    assert len(rows) == 3 and rows[0].endswith("| exact |")
    assert all(float(r.split("|")[-2]) > 30.0 for r in rows[1:])      # PSNR against the full grid
