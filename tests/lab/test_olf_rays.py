"""`python -m lab olf-rays`: the ray-space store's layout is orthonormal on
the stop (a whitened coefficient's error is the landing points' RMS error,
mm), its fit on the rays that pass holds what plain least squares loses at
a vignetted source, and a ray map served from predicted values gives the
map's kernels when the values are the map's own (and not otherwise)."""
from __future__ import annotations

import numpy as np
import pytest

from lab.olf_rays import (Layout, draw_sources, exact_predict, fit_baseline, fit_live, legendre_terms, live_rms_um,
                          main, map_values, neural_map)

LENS = "nikkor-24mm-f2"         # its wide field is vignetted: sources whose stop is partly dead


@pytest.fixture(scope="module")
def setup():
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.raymap import open_raymap
    from dcdi_core.shipped import raymap_file
    lens = load_lens(LENS)
    rm = open_raymap(raymap_file(LENS))
    return lens, rm, Layout(rm, lens)


def test_a_whitened_error_is_the_landing_points_rms_error(setup):
    from dcdi_core.optics.aiming import stop_grid
    from dcdi_core.psf.raymap import monomials
    lens, rm, layout = setup
    f, d = draw_sources(np.random.default_rng(0), 6, float(rm.diopters[0]))
    v = map_values(rm, f, d)
    w = layout.white(v)
    back = layout.unwhite(w)
    for k in ("xy", "chroma", "clip", "chief", "geometry"):
        np.testing.assert_allclose(back[k], v[k], rtol=1e-9, atol=1e-12)
    # an error of 1 um in one whitened coefficient of the sensor plane's x: 1 um RMS over the fit grid's rays
    uv = stop_grid(rm.wide_open(lens)[0], rm.recipe.fit_samples) / rm.stop_radius_mm
    mo = monomials(uv[:, 0], uv[:, 1], rm.recipe.degree, 1)
    for col in (0, 5, 40):
        e = np.zeros_like(w)
        e[:, col] = 1e-3
        moved = layout.unwhite(w + e)["xy"][:, 0]
        no = mo.shape[1]
        dx = (moved[:, :no] - v["xy"][:, 0, :no]) @ mo.T
        np.testing.assert_allclose(np.sqrt((dx ** 2).mean(axis=1)), 1e-3, rtol=1e-6)


def test_the_fit_on_passing_rays_holds_a_vignetted_lens(setup):
    lens, rm, layout = setup
    d_max = float(rm.diopters[0])
    rng = np.random.default_rng(1)
    f, d = draw_sources(rng, 400, d_max)
    v = map_values(rm, f, d)
    y, live = layout.white(v), layout.live(v)
    assert (~live.all(axis=1)).sum() > 40          # the study needs partly dead stops
    tf, td = draw_sources(rng, 100, d_max)
    tv = map_values(rm, tf, td)
    ty, tlive = layout.white(tv), layout.live(tv)
    degrees = (4, 4)
    weighed = legendre_terms(tf, td, d_max, degrees) @ fit_live(layout, f, d, y, live, d_max, degrees)
    plain = legendre_terms(tf, td, d_max, degrees) @ np.linalg.lstsq(legendre_terms(f, d, d_max, degrees), y,
                                                                     rcond=None)[0]
    got, lost = live_rms_um(layout, weighed, ty, tlive), live_rms_um(layout, plain, ty, tlive)
    assert got < lost / 5, (got, lost)
    assert fit_baseline(f, d, y, d_max).shape == (81, layout.size)


def test_a_map_served_from_its_own_values_gives_its_kernels(setup):
    from dcdi_core.optics.aperture import Aperture, stopped_down
    from dcdi_core.psf.compute import PSFSettings

    from lab.raymap_report import _map_kernel, _psnr
    lens, rm, layout = setup
    oracle = neural_map(rm, lens, layout, exact_predict(rm, layout))
    off = neural_map(rm, lens, layout, lambda f, d: exact_predict(rm, layout)(f, d) + 2e-3)
    for point, at in (({"field": 0.63, "depth_m": 1.3, "focus_m": 2.1}, lens),
                      ({"field": 0.9, "depth_m": 0.9, "focus_m": None}, stopped_down(lens, Aperture(4.0, 6, 10.0)))):
        s = PSFSettings(kernel_size=41, pupil_samples=48, pixel_pitch_mm=0.02, focus_distance_m=point["focus_m"],
                        deposit_sigma_px=0.4714)
        m = _map_kernel(rm, at, point, s)
        assert _psnr(_map_kernel(oracle, at, point, s), m) > 60.0
        assert _psnr(_map_kernel(off, at, point, s), m) < 50.0


def test_the_command_refuses_a_lens_it_does_not_know(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--lens", "no-such-lens"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no-such-lens" in err[0] and err[0].startswith("lab: error:")
    assert not any(tmp_path.iterdir())


def test_the_command_scores_a_lens_keeps_its_row_and_refuses_mixed_settings(tmp_path, capsys, monkeypatch):
    import json

    import lab.raymap_report as rr
    args = ["--out", str(tmp_path), "--lens", LENS, "--held-out", "1", "--rays", "48", "--train-sources", "256"]
    assert main(args) == 0
    table = capsys.readouterr().out
    assert f"| `{LENS}` |" in table and "| all 1 lenses, 1 points |" in table
    row = json.loads((tmp_path / "result.json").read_text())["lenses"][0]
    assert row["olf_vs_map"][0] > 40.0 and row["store_val_um"] < 1.0 and len(row["points"]) == 1
    # run again: the row is kept, nothing is traced; its store written as an OLF file that serves the lens
    monkeypatch.setattr(rr, "_pitch_for", lambda *a: (_ for _ in ()).throw(AssertionError("traced again")))
    olf = tmp_path / "olf.npz"
    assert main(args + ["--export", str(olf)]) == 0
    assert json.loads((tmp_path / "result.json").read_text())["lenses"][0]["olf"] == row["olf"]
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.rayfield import RayFieldOLF
    from dcdi_core.psf.sources import psf_source
    f = RayFieldOLF.load(olf)
    assert f.lens_ids == [LENS] and f.entry(LENS)["held_out"]["psnr_8bit"] == row["olf"]
    src = psf_source(load_lens(LENS), olf_file=str(olf), pixel_pitch_mm=0.01)
    assert src.kind == "olf" and "in ray space" in src.message
    # other training settings into the same folder: refused in one line, the kept data untouched
    capsys.readouterr()
    kept = (tmp_path / LENS / "data.npz").read_bytes()
    assert main(args[:-1] + ["300"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "train" in err[0] and err[0].startswith("lab: error:")
    assert (tmp_path / LENS / "data.npz").read_bytes() == kept
