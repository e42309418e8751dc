"""The reference renderer traced through the lens (lab/traced_render.py):
the lens traced backward retraces the forward ray, a plane in focus renders
as the pinhole does, an occluding edge mixes a pixel's pupil cone, nothing is
ever NaN, the pupil cone holds every ray the lens passes, and a bad option
ends in one line before any work."""
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.optics.aiming import start_plane_z
from dcdi_core.optics.aperture import Aperture, stopped_down
from dcdi_core.optics.lens import load_lens
from dcdi_core.optics.paraxial import refocused
from dcdi_core.optics.trace import trace
from dcdi_core.render.geometry import ImageGeometry
from lab import traced_render as tr


# ------------------------------------------------------------------ the lens reversed
def _aspheric(lens, odd: bool):
    """``lens`` with a conic and even (or odd) aspheric terms on its second and
    next-to-last surfaces (no catalogue lens is aspheric)."""
    s = list(lens.surfaces)
    for i in (1, len(s) - 2):
        sd = s[i].semi_diameter_mm
        if odd:
            s[i] = replace(s[i], conic=-0.6, odd_aspheric_coefficients=(0.0, 1e-3 / sd, 0.0, -2e-3 / sd ** 3))
        else:
            s[i] = replace(s[i], conic=-0.6, aspheric_coefficients=(1e-3 / sd, -2e-3 / sd ** 3, 1e-3 / sd ** 5))
    return lens.with_surfaces(s)


def _round_trip(lens, n=2000, seed=0):
    """Largest position (mm) and direction errors of rays traced forward to
    the sensor, then from there backward through the reversed lens, against
    the original rays on their launch plane; and how many came back."""
    rng = np.random.default_rng(seed)
    z0, r0 = start_plane_z(lens), lens.surfaces[0].semi_diameter_mm
    o = np.stack([rng.uniform(-0.7, 0.7, n) * r0, rng.uniform(-0.7, 0.7, n) * r0, np.full(n, z0)], -1)
    d = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), np.ones(n)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    wl = rng.uniform(420.0, 680.0, n)
    fwd = trace(lens, o, d, wl)
    v = fwd.valid
    rev, z_last = tr.reversed_lens(lens)
    back_o, back_d, ok = tr.trace_backward(rev, z_last, fwd.position_mm[v], -fwd.direction[v], wl[v])
    back_o = back_o * 1000.0
    back_o[:, 2] *= -1.0                               # the scene's frame (m, z to the object) -> the lens's
    back_d = back_d * np.array([1.0, 1.0, -1.0])
    return (float(np.abs(back_o[ok] - o[v][ok]).max()), float(np.abs(back_d[ok] + d[v][ok]).max()),
            int(v.sum()), int(ok.sum()))


@pytest.mark.parametrize("lens_id, asphere", [("zeiss-planar-50mm-f1-4", None), ("nikkor-24mm-f2", None),
                                              ("mos-s1", None), ("6p", "even"), ("6p", "odd"),
                                              ("zeiss-sonnar-50mm-f1-5", "even")])
def test_a_ray_traced_forward_then_backward_comes_back(lens_id, asphere):
    lens = load_lens(lens_id)
    if asphere:
        lens = _aspheric(lens, asphere == "odd")
        assert any(s.is_aspheric for s in lens.surfaces)
    err_pos, err_dir, arrived, back = _round_trip(lens)
    assert arrived > 100 and back == arrived
    assert err_pos < 1e-9 and err_dir < 1e-12


def test_the_reversal_flips_every_sag_term():
    """A reversal that kept the aspheric terms' sign would not retrace the rays (the test above can fail)."""
    lens = _aspheric(load_lens("6p"), odd=False)
    rev, _ = tr.reversed_lens(lens)
    wrong = rev.with_surfaces([replace(s, aspheric_coefficients=tuple(-a for a in s.aspheric_coefficients))
                               for s in rev.surfaces])
    real = tr.reversed_lens
    try:
        tr.reversed_lens = lambda lens_, exit_z_mm=None: (wrong, float(lens_.vertex_z_mm[-1]))
        assert _round_trip(lens)[0] > 1e-3
    finally:
        tr.reversed_lens = real


# ------------------------------------------------------------------ the traced render
def test_a_plane_in_focus_renders_as_the_pinhole_does():
    """A Tessar at f/16 focused at 2 m on a textured plane at 2 m, a 15 x 15 px
    crop on the axis: the traced render equals the pinhole render of the
    focused lens within the noise (a flipped or shifted image would not)."""
    lens = refocused(stopped_down(load_lens("zeiss-jena-tessar-50mm-f2-8"), Aperture(16.0)), 2.0)
    pitch = 0.05
    g = ImageGeometry.from_pixel_pitch(lens, 15, 15, pitch)
    tan_px = pitch / tr.ideal_scale_mm(lens)
    scene = tr.Scene((tr.Plane(2.0, tr.Texture(period_m=7 * tan_px * 2.0, checker_m=13 * tan_px * 2.0, phase=0.7,
                                               gradient=0.02 / (tan_px * 2.0))),))
    traced = tr.traced_render(lens, scene, g, rays=64, seed=3)
    pin, depth = tr.pinhole_render(lens, scene, g, supersample=8)
    assert np.allclose(depth, 2.0)
    assert traced.image.std() > 0.05                   # the texture is resolved
    noise = np.abs(traced.halves[0] - traced.halves[1]).max()
    err = np.abs(traced.image - pin).max()
    assert err < max(0.03, noise), (err, noise)
    flipped = np.abs(traced.image - pin[::-1, ::-1]).max()
    assert flipped > 5 * err


def test_an_occluding_edge_mixes_the_pixels_pupil_cone():
    """A white plane at 5 m in focus, a black half-plane at 1 m over the
    right half (its edge on the axis): the axial pixel sees half of each,
    the far left only white, the far right only black."""
    lens = refocused(load_lens("mos-s1"), 5.0)
    g = ImageGeometry.from_pixel_pitch(lens, 1, 21, 0.05)
    scene = tr.Scene((tr.Plane(5.0, (1.0, 1.0, 1.0)), tr.Plane(1.0, (0.0, 0.0, 0.0), region=((1.0, 0.0, 0.0),))))
    img = tr.traced_render(lens, scene, g, rays=1024, seed=1).image[0]
    assert np.allclose(img[10], 0.5, atol=0.03), img[10]
    assert np.allclose(img[0], 1.0, atol=1e-12) and np.allclose(img[-1], 0.0, atol=1e-12)
    assert (np.diff(img[:, 1]) <= 0.05).all()          # white to black across the edge


def test_nothing_is_nan_where_rays_miss_everything_or_no_ray_passes():
    """A sphere alone (background 0) on a frame reaching beyond the lens's
    field: finite everywhere, 0 where no ray meets it; the pinhole's depth
    inf there. A uniform plane of radiance 1 renders exactly 1 wherever a
    ray passes, in the vignetted corners too (the engine's normalisation:
    by the rays that arrive)."""
    lens = refocused(load_lens("nikkor-24mm-f2"), 1.5)
    g = ImageGeometry.from_pixel_pitch(lens, 11, 17, 3.0)      # corners at field 1.3
    scene = tr.Scene((tr.Sphere((0.0, 0.0, 3.0), 0.6, (5.0, 4.0, 3.0)),))
    t = tr.traced_render(lens, scene, g, rays=16, seed=0)
    assert np.isfinite(t.image).all() and np.isfinite(t.halves).all() and (t.image >= 0).all()
    assert np.abs(t.image[5, 8] - [5.0, 4.0, 3.0]).max() < 1e-9     # every ray of the centre meets the sphere
    assert t.image[0, 0].max() == 0.0 and t.image[5, 0].max() == 0.0
    assert (t.passed == 0).any() and (t.passed[5] > 0).all()   # the corners are beyond the lens's reach
    pin, depth = tr.pinhole_render(lens, scene, g, supersample=2)
    assert np.isfinite(pin).all() and np.isinf(depth[0, 0]) and np.isfinite(depth[5, 8])
    flat = tr.Scene((tr.Plane(1.5, (1.0, 1.0, 1.0)),))
    g2 = ImageGeometry.full_sensor(lens, 8, 12)
    u = tr.traced_render(lens, flat, g2, rays=16, seed=0)
    assert u.passed[0, 0] < 0.8 * u.passed[4, 6]               # vignetted corner, still 1
    assert np.abs(u.image - 1.0).max() < 1e-12


def test_the_pupil_cone_holds_every_ray_the_lens_passes():
    """Dense fans of backward rays from sensor points (on a diagonal: the cone
    rotated) of a vignetting lens wide open: every one that passes lies in
    the disc the cones give, which is not much larger than the beam."""
    lens = refocused(load_lens("nikkor-24mm-f2"), 1.5)
    sd = lens.sensor.semi_diagonal_mm
    cones = tr.pupil_cones(lens, sd * 1.02, pitch_mm=0.3)
    rev, z_last = tr.reversed_lens(lens)
    u = np.linspace(-0.7, 0.7, 161)
    kx, ky = np.meshgrid(u, u)
    for h in (0.0, 0.37 * sd, 0.81 * sd, sd):
        ex, ey = math.sin(math.radians(40)), math.cos(math.radians(40))
        c, rad = cones.at(np.array(h))
        inside = np.hypot(kx - c * ex, ky - c * ey) <= rad
        n = kx.size
        o = np.stack([np.full(n, h * ex), np.full(n, h * ey), np.full(n, lens.sensor_z_mm)], -1)
        d = np.stack([kx.ravel(), ky.ravel(), -np.sqrt(1 - kx.ravel() ** 2 - ky.ravel() ** 2)], -1)
        ok = np.zeros(n, bool)
        for wl in (400.0, 550.0, 700.0):
            ok |= tr.trace_backward(rev, z_last, o, d, wl)[2]
        assert ok.any()
        assert not (ok & ~inside.ravel()).any(), h
        assert inside.sum() < 4.5 * ok.sum()            # the cat's eye of the corner: about 1 in 4 used


# ------------------------------------------------------------------ the command
@pytest.mark.parametrize("argv, words", [
    (["--lenses", "no-such-lens"], "no-such-lens"),
    (["--lenses", "zeiss-jena-tessar-50mm-f2-8", "--f-number", "1.4"], "f-number"),
    (["--lenses", "mos-s1", "--focus", "0.3"], "--focus"),
    (["--lenses", "mos-s1", "--rays", "7"], "--rays"),
])
def test_bad_input_is_one_line_before_any_work(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tr, "score_case", lambda *a, **k: pytest.fail("work began"))
    out = tmp_path / "out"
    assert tr.main(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lab: error:") and "\n" not in err and words in err, err
    assert not out.exists()


def test_the_command_writes_its_table(tmp_path, capsys):
    """One lens, one focus, wide open, a tiny frame: a row of finite scores in
    the Markdown and JSON files (through `python -m lab`'s entry point)."""
    from lab import cli
    out = tmp_path / "out"
    assert cli.main(["traced-render", "--lenses", "mos-s2", "--focus", "1.5", "--f-number", "open",
                     "--size", "16", "24", "--rays", "8", "--boost", "2", "--out", str(out)]) == 0
    rows = json.loads((out / "traced-render.json").read_text())["rows"]
    assert len(rows) == 1 and rows[0]["lens"] == "mos-s2"
    assert all(math.isfinite(rows[0][k]) for k in ("psnr_frame", "psnr_edge", "floor_frame"))
    assert "| mos-s2 |" in (out / "traced-render.md").read_text()
