"""The iris (optics.aperture): a lens stopped down to an f-number, round or
bladed; its PSFs, fingerprints, the stores that do not serve it, the CLI."""
import math

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.aiming import stop_grid
from dcdi_core.optics.aperture import Aperture, inside_iris, stopped_down, wide_open_f_number
from dcdi_core.optics.lens import lens_fingerprint, load_lens
from dcdi_core.optics.paraxial import first_order
from dcdi_core.optics.trace import trace
from dcdi_core.psf.compute import PSFSettings, psf
from dcdi_core.psf.sources import psf_source
from tests.support.cli import run_cli

# a defocused point: the 6P focused at 2 m, a point at 0.7 m (a blur of ~10-30 px at 12.2 um)
SETTINGS = PSFSettings(kernel_size=81, pupil_samples=96, n_wavelengths=3, focus_distance_m=2.0)


def _kernel(lens, **kw):
    k = psf(lens, depth_m=0.7, field=0.0, settings=SETTINGS, **kw).psf.sum(axis=0)
    return k / k.sum()


def _rms_radius_px(k):
    n = k.shape[-1]
    yy, xx = np.mgrid[:n, :n]
    cy, cx = (k * yy).sum(), (k * xx).sum()
    return float(np.sqrt((k * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum()))


@pytest.mark.parametrize("lens_id", ["6p", "mos-s1", "double-gauss"])
@pytest.mark.parametrize("f_number_factor", [1.0, 1.5, 4.0])
def test_the_stopped_lens_has_the_f_number_asked_for(lens_id, f_number_factor):
    lens = load_lens(lens_id)
    n0 = wide_open_f_number(lens)
    stopped = stopped_down(lens, Aperture(n0 * f_number_factor))
    assert first_order(stopped).f_number == pytest.approx(n0 * f_number_factor, rel=1e-9)
    # the focal length and every other surface as prescribed
    assert first_order(stopped).effective_focal_length_mm == pytest.approx(first_order(lens).effective_focal_length_mm)
    others = [i for i in range(len(lens.surfaces)) if i != lens.stop_index]
    assert [stopped.surfaces[i] for i in others] == [lens.surfaces[i] for i in others]
    assert stopped.iris.startswith("f/") and stopped.iris in stopped.name


def test_nothing_asked_is_the_lens_itself_and_wider_is_refused():
    lens = load_lens("6p")
    assert stopped_down(lens, Aperture()) is lens
    with pytest.raises(InputRangeError, match=r"f-number of 6p .*6p\.toml.*f/1\.64 \(its widest"):
        stopped_down(lens, Aperture(1.2))
    for bad in (dict(f_number=0.0), dict(f_number=math.nan), dict(f_number=1e9), dict(f_number=True),
                dict(blades=2), dict(blades=33), dict(blades=6.0), dict(blades=6, rotation_deg=math.inf)):
        with pytest.raises(InputRangeError):
            Aperture(**bad)


def test_fingerprints_differ_by_f_number_and_blades_and_not_otherwise(monkeypatch):
    lens = load_lens("6p")
    prints = {lens_fingerprint(stopped_down(lens, a)) for a in
              (Aperture(), Aperture(2.8), Aperture(4.0), Aperture(4.0, 6), Aperture(4.0, 6, 30.0))}
    assert len(prints) == 5
    assert lens_fingerprint(stopped_down(lens, Aperture(4.0))) == lens_fingerprint(stopped_down(lens, Aperture(4.0)))
    # the OLF in ray space serves it stopped down; the basis and the network know it wide open and say why not
    src = psf_source(stopped_down(lens, Aperture(4.0, 6)))
    assert src.kind == "olf" and "in ray space, f/4, 6 blades" in src.message, src.message
    import dcdi_core.psf.sources as sources
    monkeypatch.setattr(sources, "olf_rays_file", lambda: None)
    src = psf_source(stopped_down(lens, Aperture(4.0, 6)))
    assert src.kind == "trace"
    assert "6p is stopped down (f/4, 6 blades)" in src.message
    assert psf_source(lens).kind != "trace"


def test_the_defocus_blur_scales_as_one_over_the_f_number():
    lens = load_lens("6p")
    r = {n: _rms_radius_px(_kernel(stopped_down(lens, Aperture(n)))) for n in (2.0, 4.0, 8.0)}
    # geometric defocus: the blur's radius is proportional to the pupil's; within 25 % between N and 4N
    assert 4.0 / 1.25 <= r[2.0] / r[8.0] <= 4.0 * 1.25
    assert 2.0 / 1.25 <= r[2.0] / r[4.0] <= 2.0 * 1.25


def _rotated(k, deg):
    """``k`` turned by ``deg`` about its centroid (bilinear; zero outside)."""
    n = k.shape[-1]
    yy, xx = np.mgrid[:n, :n].astype(float)
    cy, cx = (k * yy).sum() / k.sum(), (k * xx).sum() / k.sum()
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    y = cy + c * (yy - cy) - s * (xx - cx)
    x = cx + s * (yy - cy) + c * (xx - cx)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    out = np.zeros_like(k)
    for dy in (0, 1):
        for dx in (0, 1):
            w = (1 - abs(y - y0 - dy)) * (1 - abs(x - x0 - dx))
            yi, xi = y0 + dy, x0 + dx
            ok = (yi >= 0) & (yi < n) & (xi >= 0) & (xi < n)
            out[ok] += w[ok] * k[yi[ok], xi[ok]]
    return out


def _support(k):
    """The kernel's lit pixels (above 5 % of its peak): the shape of the iris, without the
    ray sampling's noise inside it."""
    return (k > 0.05 * k.max()).astype(float)


def _unlike(m, deg):
    """Pixels where the support ``m`` and itself turned by ``deg`` differ."""
    return float(np.abs(m - (_rotated(m, deg) > 0.5)).sum())


@pytest.mark.parametrize("blades", [5, 6, 8])
def test_a_bladed_iris_gives_its_polygon_to_the_defocused_psf(blades):
    lens = load_lens("6p")
    m = _support(_kernel(stopped_down(lens, Aperture(2.0, blades))))
    step = 360.0 / blades
    # the n-gon: alike after a turn by its corners' spacing, unlike after half of it
    # (measured: 16-19 against 56-123 pixels of 430-530), where the round stop is alike at both
    assert _unlike(m, step) < 0.4 * _unlike(m, step / 2)
    if blades <= 6:          # an octagon lies within 8 % of its circle: the pixel grid's own anisotropy is as large
        round_ = _support(_kernel(stopped_down(lens, Aperture(2.0))))
        assert _unlike(round_, step / 2) < 0.6 * _unlike(m, step / 2)


def test_the_blade_rotation_turns_the_polygon():
    lens = load_lens("6p")
    m0 = _support(_kernel(stopped_down(lens, Aperture(2.0, 6, 0.0))))
    m30 = _support(_kernel(stopped_down(lens, Aperture(2.0, 6, 30.0))))
    # turned by 30 degrees the iris gives the same hexagon turned by 30 degrees
    assert np.abs((_rotated(m0, 30.0) > 0.5) - m30).sum() < 0.4 * np.abs(m0 - m30).sum()


@pytest.mark.parametrize("blades", [3, 6, 9])
def test_inside_iris_is_the_inscribed_polygon(blades):
    rng = np.random.default_rng(blades)
    x, y = rng.uniform(-1, 1, (2, 400_000))
    inside = inside_iris(x, y, blades, 17.0, 1.0)
    area = blades / 2 * math.sin(2 * math.pi / blades)
    assert inside.mean() * 4 == pytest.approx(area, rel=0.01)
    assert not (inside & (x * x + y * y > 1.0)).any()
    # its corners lie on the circle, one at 17 degrees from +y towards +x
    a = np.radians(17.0 + 360.0 * np.arange(blades) / blades)
    assert inside_iris(0.999 * np.sin(a), 0.999 * np.cos(a), blades, 17.0, 1.0).all()
    assert not inside_iris(1.001 * np.sin(a), 1.001 * np.cos(a), blades, 17.0, 1.0).any()


def test_pupil_samples_fill_the_polygon_and_the_tracer_clips_to_it():
    lens = stopped_down(load_lens("6p"), Aperture(2.8, 5, 0.0))
    stop = lens.surfaces[lens.stop_index]
    g = stop_grid(lens, 200)
    full = stop_grid(stopped_down(load_lens("6p"), Aperture(2.8)), 200)
    assert len(g) / len(full) == pytest.approx(5 / 2 * math.sin(2 * math.pi / 5) / math.pi, rel=0.01)
    assert inside_iris(g[:, 0], g[:, 1], 5, 0.0, stop.semi_diameter_mm).all()
    # a stop in front (first surface): rays parallel to the axis meet the stop where they start
    from dataclasses import replace
    plate = replace(lens.surfaces[lens.stop_index], radius_mm=math.inf, thickness_mm=1.0)
    r = stop.semi_diameter_mm
    pts = np.array([[0.0, 0.95 * r], [0.0, -0.95 * r]])     # a corner at +y; an edge's middle at -y
    o = np.stack([pts[:, 0], pts[:, 1], np.full(2, -1.0)], axis=-1)
    d = np.tile([0.0, 0.0, 1.0], (2, 1))
    b = trace(lens.with_surfaces((plate,) + lens.surfaces[lens.stop_index + 1:]), o, d, 550.0)
    assert b.valid.tolist() == [True, False]


def test_cli_psf_takes_the_aperture_and_refuses_a_wider_one(capsys):
    code, out, err = run_cli(capsys, "psf", "6p", "--depth", "0.7", "--field", "0", "--f-number", "4",
                             "--blades", "6", "--rays", "24", "--wavelengths", "3", "--json")
    assert code == 0, err
    assert "f/4, 6 blades" in err
    code, out, err = run_cli(capsys, "psf", "6p", "--depth", "0.7", "--field", "0", "--f-number", "1.2")
    assert code != 0 and out == ""
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1 and "f/1.64" in lines[0] and "6p.toml" in lines[0]
    code, _, err = run_cli(capsys, "psf", "6p", "--depth", "0.7", "--field", "0", "--blades", "2")
    assert code != 0 and "blades" in err


def test_a_turned_iris_is_another_lens_to_every_cache():
    """The blades' turn is in the lens's name (a preview's key is made of
    it) and in the source cache's key: a turn gives a new source."""
    from dcdi_core import app
    from dcdi_core.render.geometry import ImageGeometry
    lens = load_lens("zeiss-jena-tessar-50mm-f2-8")
    a, b = (stopped_down(lens, Aperture(8.0, 6, r)) for r in (0.0, 15.0))
    assert a.iris == "f/8, 6 blades" and b.iris == "f/8, 6 blades turned 15 deg"
    cache = app.SourceCache()
    geom = ImageGeometry.full_sensor(lens, 60, 90)
    req = app.PSFRequest(settings=PSFSettings(pupil_samples=8, n_wavelengths=3))
    first, turned = cache.chosen(a, geom, req), cache.chosen(b, geom, req)
    assert turned is not first and cache.chosen(a, geom, req) is first
    assert turned.library.lens.surfaces[turned.library.lens.stop_index].blade_rotation_deg == 15.0
