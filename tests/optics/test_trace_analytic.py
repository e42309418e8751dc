"""The tracer against closed-form geometry (no code shared with the tracer)."""
import math

import numpy as np
import pytest
from conftest import singlet_dict

from dcdi_core.optics import surfaces as S
from dcdi_core.optics.lens import Lens
from dcdi_core.optics.trace import trace

WL = 587.5618


def _ray(y, z0=-1.0, angle=0.0):
    return np.array([0.0, y, z0]), np.array([0.0, math.sin(angle), math.cos(angle)])


def _analytic_plano_convex(h, R, t, back, n):
    """Height on the sensor of a ray parallel to the axis at height h through a
    sphere (radius R, vertex at z=1) then a plane at z = 1 + t, by scalar Snell."""
    z1 = R - math.sqrt(R * R - h * h)            # sag of the sphere at h
    i = math.asin(h / R)                          # incidence angle (normal through the centre)
    r = math.asin(math.sin(i) / n)
    slope = math.tan(i - r)                       # the ray now descends towards the axis
    y2 = h - (t - z1) * slope
    out = math.asin(n * math.sin(i - r))
    return y2 - back * math.tan(out)


@pytest.mark.parametrize("h", [0.001, 1.0, 3.0, 4.9])
def test_singlet_matches_scalar_snell_to_1e9_mm(h):
    lens = Lens.from_dict(singlet_dict(r1=50.0, t=5.0, back=40.0, nd=1.5))
    o, d = _ray(h)
    b = trace(lens, o, d, WL)
    assert b.valid
    expected = _analytic_plano_convex(h, 50.0, 5.0, 40.0, 1.5)
    assert abs(b.position_mm[1] - expected) < 1e-9
    assert abs(b.position_mm[2] - lens.sensor_z_mm) < 1e-12
    assert abs(np.linalg.norm(b.direction) - 1.0) < 1e-14


def test_paraboloid_conic_hits_where_geometry_says():
    # k = -1: z = h^2 / (2 R) exactly; normal slope dz/dr = h / R
    R, h = 20.0, 6.0
    lens = Lens.from_dict(singlet_dict(r1=R, conic=-1.0, sd=8.0, t=10.0, back=30.0, stop_first=False))
    o, d = _ray(h)
    b = trace(lens, o, d, WL, upto_surface=0)
    assert b.valid
    assert abs(b.position_mm[2] - h * h / (2 * R)) < 1e-12
    # after refraction: compare the direction with scalar Snell about the paraboloid normal
    full = trace(lens, o, d, WL)
    normal_angle = math.atan(h / R)
    r = math.asin(math.sin(normal_angle) / 1.5)
    inside = normal_angle - r
    # second surface is a plane at z = 1 + 10: exit angle by Snell
    z1 = h * h / (2 * R)
    y2 = h - (10.0 - z1) * math.tan(inside)
    out = math.asin(1.5 * math.sin(inside))
    assert abs(full.position_mm[1] - (y2 - 30.0 * math.tan(out))) < 1e-9


def test_even_asphere_newton_hits_the_surface():
    # plane with a4 r^4 only: z = a4 h^4 exactly, slope 4 a4 h^3
    a4 = 1e-3
    h = 3.0
    lens = Lens.from_dict(singlet_dict(r1=math.inf, asph=[0.0, a4], sd=5.0, t=5.0, back=20.0, stop_first=False))
    o, d = _ray(h)
    b = trace(lens, o, d, WL, upto_surface=0)
    assert b.valid
    assert abs(b.position_mm[2] - a4 * h ** 4) < 1e-12
    full = trace(lens, o, d, WL)
    tilt = math.atan(4 * a4 * h ** 3)
    r = math.asin(math.sin(tilt) / 1.5)
    inside = tilt - r
    y2 = h - (5.0 - a4 * h ** 4) * math.tan(inside)
    out = math.asin(1.5 * math.sin(inside))
    assert abs(full.position_mm[1] - (y2 - 20.0 * math.tan(out))) < 1e-9


def test_radius_1e15_equals_plane():
    flat = Lens.from_dict(singlet_dict(r1=math.inf))
    huge = Lens.from_dict(singlet_dict(r1=1e15))
    o = np.array([[0.0, 2.0, -1.0], [1.0, -3.0, -1.0]])
    d = np.array([[0.0, 0.1, 1.0], [0.05, 0.02, 1.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a, b = trace(flat, o, d, WL), trace(huge, o, d, WL)
    assert a.valid.all() and b.valid.all()
    assert np.abs(a.position_mm - b.position_mm).max() < 1e-9


def test_float32_agrees_with_float64():
    lens = Lens.from_dict(singlet_dict())
    y = np.linspace(-4.5, 4.5, 101)
    o = np.stack([np.zeros_like(y), y, -np.ones_like(y)], -1)
    d = np.array([0.0, 0.05, 1.0]) / math.hypot(0.05, 1.0)
    a = trace(lens, o, d, WL)
    b = trace(lens, o, d, WL, dtype=np.float32)
    assert b.position_mm.dtype == np.float64 or b.position_mm.dtype == np.float32
    assert (a.status == b.status).all()
    assert np.abs(a.position_mm - b.position_mm).max() < 1e-3


def test_batched_leading_shape_and_wavelength_broadcast():
    lens = Lens.from_dict(singlet_dict())
    o = np.zeros((2, 3, 1, 5, 3))
    o[..., 1] = np.linspace(0.5, 4.0, 5)
    o[..., 2] = -1.0
    d = np.array([0.0, 0.0, 1.0])
    wl = np.array([450.0, 550.0, 650.0])[:, None]
    b = trace(lens, o, d, wl)
    assert b.shape == (2, 3, 3, 5)
    # dispersion: blue focuses shorter, so a marginal ray lands lower (more negative)
    y = b.position_mm[0, 0, :, -1, 1]
    assert y[0] < y[1] < y[2]


def test_status_codes_are_exact():
    lens = Lens.from_dict(singlet_dict(sd=10.0))  # stop semi-diameter 5
    o = np.array([[0.0, 1.0, -1.0],      # fine
                  [0.0, 7.0, -1.0],      # outside the stop (surface 0)
                  [0.0, 1.0, -1.0]])     # travelling backwards
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    b = trace(lens, o, d, WL)
    assert b.status.tolist() == [S.OK, S.VIGNETTED, S.BACKWARD]
    assert b.failed_surface.tolist() == [-1, 0, 0]
    assert np.isfinite(b.position_mm).all() and np.isfinite(b.direction).all()
