"""Each surface kind (dcdi_core.optics.profiles) against an independent
computation: the sphere's intersection in closed form (the ray against the
sphere about its centre), the conic's on its implicit equation, the even
asphere's by a bracketing root-finder (scipy's brentq) on its sag; each
normal against a finite-difference gradient of the sag; the kind chosen for
each surface of a prescription."""
import math

import numpy as np
import pytest

from dcdi_core.optics import surfaces as S
from dcdi_core.optics.profiles import Conic, EvenAsphere, Plane, Sphere, profile_of


def rays(n=400, seed=0, spread=3.0, tilt=0.2):
    """Rays at the vertex plane z = 0: positions (xs, ys), unit directions."""
    rng = np.random.default_rng(seed)
    xs, ys = rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n)
    d = np.stack([rng.uniform(-tilt, tilt, n), rng.uniform(-tilt, tilt, n), np.ones(n)])
    d /= np.linalg.norm(d, axis=0)
    return xs, ys, d[0], d[1], d[2]


def no_kill(mask, code):
    assert not np.asarray(mask).any(), (int(np.asarray(mask).sum()), S.STATUS_NAMES[code])


def test_sphere_root_is_the_closed_form_intersection():
    R = 12.0
    prof = Sphere(1 / R)
    xs, ys, dx, dy, dz = rays()
    t = prof.root(xs, ys, dx, dy, dz, no_kill, 1e-12, 30)
    # the ray p + t d against |p - (0, 0, R)| = R, the root nearer the vertex plane
    px, py, pz = xs, ys, np.zeros_like(xs) - R
    b = px * dx + py * dy + pz * dz
    c = px * px + py * py + pz * pz - R * R
    closed = -b - np.sign(R) * np.sqrt(b * b - c)
    closed = np.where(np.abs(-b + np.sqrt(b * b - c)) < np.abs(closed), -b + np.sqrt(b * b - c), closed)
    np.testing.assert_allclose(t, closed, rtol=0, atol=1e-12)
    nx, ny, nz = prof.normal(xs + t * dx, ys + t * dy, t * dz, None, np.dtype(np.float64))
    # the sphere's normal points from the hit to the centre (along +z at the vertex)
    hx, hy, hz = xs + t * dx, ys + t * dy, t * dz - R
    norm = np.sqrt(hx * hx + hy * hy + hz * hz)
    np.testing.assert_allclose(np.stack([nx, ny, nz]), np.stack([-hx, -hy, -hz]) / norm, atol=1e-12)


@pytest.mark.parametrize("k", [-1.0, -0.6, 0.8, 2.5])
def test_conic_root_lies_on_its_implicit_surface(k):
    c = 1 / 15.0
    prof = Conic(c, k)
    xs, ys, dx, dy, dz = rays(spread=2.5)
    t = prof.root(xs, ys, dx, dy, dz, no_kill, 1e-12, 30)
    x, y, z = xs + t * dx, ys + t * dy, t * dz
    # c (x^2 + y^2) + (1 + k) c z^2 - 2 z = 0 on the conic
    np.testing.assert_allclose(c * (x * x + y * y) + (1 + k) * c * z * z - 2 * z, 0.0, atol=1e-12)
    np.testing.assert_allclose(z, prof.sag(x * x + y * y), atol=1e-12)   # the sheet with the vertex
    _normal_is_the_sags_gradient(prof, x, y, z)


def _normal_is_the_sags_gradient(prof, x, y, z, h=1e-6):
    nx, ny, nz = prof.normal(x, y, z, x * x + y * y, np.dtype(np.float64))
    sx = (prof.sag((x + h) ** 2 + y * y) - prof.sag((x - h) ** 2 + y * y)) / (2 * h)
    sy = (prof.sag(x * x + (y + h) ** 2) - prof.sag(x * x + (y - h) ** 2)) / (2 * h)
    want = np.stack([-sx, -sy, np.ones_like(sx)])
    want /= np.linalg.norm(want, axis=0)
    np.testing.assert_allclose(np.stack([nx, ny, nz]), want, atol=1e-7)
    np.testing.assert_allclose(np.sqrt(nx * nx + ny * ny + nz * nz), 1.0, atol=1e-12)


def _root_is_brentqs(prof):
    """The kind's roots of 60 rays against scipy's bracketing brentq on its
    sag, to 1e-10 mm; returns the hits (x, y, z)."""
    from scipy.optimize import brentq
    xs, ys, dx, dy, dz = rays(n=60, spread=2.0)
    t = prof.root(xs, ys, dx, dy, dz, no_kill, 1e-12, 30)
    for i in range(len(xs)):
        def g(tt, i=i):
            x, y = xs[i] + tt * dx[i], ys[i] + tt * dy[i]
            return tt * dz[i] - float(prof.sag(x * x + y * y))
        ref = brentq(g, -5.0, 5.0, xtol=1e-14)
        assert abs(t[i] - ref) < 1e-10, (i, t[i], ref)
    return xs + t * dx, ys + t * dy, t * dz


@pytest.mark.parametrize("c, k, coeffs", [(1 / 20.0, 0.0, (0.0, 1e-4, -2e-7)), (-1 / 30.0, -0.5, (1e-3, -1e-6)),
                                          (0.0, 0.0, (2e-3,))])
def test_even_asphere_root_is_a_bracketing_root_finders(c, k, coeffs):
    prof = EvenAsphere(c, k, coeffs)
    _normal_is_the_sags_gradient(prof, *_root_is_brentqs(prof))


def test_plane_is_the_vertex_plane():
    prof = Plane()
    xs, ys, dx, dy, dz = rays(n=10)
    assert prof.root(xs, ys, dx, dy, dz, no_kill, 1e-12, 30) is None
    assert prof.normal(xs, ys, None, None, np.dtype(np.float32)) == (0.0, 0.0, 1.0)
    assert not prof.curved and (prof.sag(np.linspace(0, 4, 5)) == 0).all()


def test_a_ray_that_misses_the_sphere_is_killed_as_missed():
    prof = Sphere(1 / 2.0)
    xs, ys, dx, dy, dz = np.array([0.0, 5.0]), np.array([0.0, 0.0]), np.zeros(2), np.zeros(2), np.ones(2)
    killed = []
    prof.root(xs, ys, dx, dy, dz, lambda m, code: killed.append((m.tolist(), code)), 1e-12, 30)
    assert killed == [([False, True], S.MISSED)]


def test_each_surface_gets_its_kind():
    from dcdi_core.optics.lens import load_lens
    from conftest import singlet_dict
    from dcdi_core.optics.lens import Lens
    kinds = [type(profile_of(s)).__name__ for s in load_lens("mos-s1").surfaces]
    assert kinds[0] == "Plane" and "Sphere" in kinds
    lens = Lens.from_dict(singlet_dict(conic=-0.5))
    assert [type(profile_of(s)).__name__ for s in lens.surfaces] == ["Plane", "Conic", "Plane"]
    lens = Lens.from_dict(singlet_dict(asph=[0.0, 1e-5]))
    assert type(profile_of(lens.surfaces[1])).__name__ == "EvenAsphere"
    assert math.isclose(profile_of(lens.surfaces[1]).sag(4.0), float(lens.surfaces[1].sag(4.0)))


# ------------------------------------------------------------------ a new kind in one file: the odd asphere
@pytest.mark.parametrize("c, k, coeffs", [(1 / 25.0, 0.0, (0.0, 0.0, 1e-4)), (-1 / 40.0, -0.3, (0.0, 0.0, -2e-4, 1e-5)),
                                          (0.0, 0.0, (0.02,))])
def test_odd_asphere_root_is_a_bracketing_root_finders(c, k, coeffs):
    from dcdi_core.optics.profiles import OddAsphere
    prof = OddAsphere(c, k, coeffs)
    x, y, z = _root_is_brentqs(prof)
    far = np.hypot(x, y) > 1e-3                        # the cone's tip (b_1 r) has no normal at the axis
    _normal_is_the_sags_gradient(prof, x[far], y[far], z[far])


def test_an_odd_asphere_of_even_powers_is_the_even_asphere():
    """b_2 r^2 + b_4 r^4 is a_1 r^2 + a_2 r^4: the same lens, traced to 1e-9 mm."""
    from conftest import singlet_dict
    from dcdi_core.optics.lens import Lens
    from dcdi_core.optics.trace import trace
    from dcdi_core.optics.lens import lens_fingerprint
    even = Lens.from_dict(singlet_dict(asph=[1e-3, -2e-6]))
    d = singlet_dict()
    d["surface"][1]["odd_aspheric_coefficients"] = [0.0, 1e-3, 0.0, -2e-6]
    odd = Lens.from_dict(d)
    assert type(profile_of(odd.surfaces[1])).__name__ == "OddAsphere"
    assert lens_fingerprint(odd) != lens_fingerprint(even)
    xs, ys, dx, dy, dz = rays(n=500, spread=4.0, tilt=0.1)
    o = np.stack([xs, ys, np.full_like(xs, -5.0)], -1)
    dirs = np.stack([dx, dy, dz], -1)
    a, b = trace(even, o, dirs, 550.0), trace(odd, o, dirs, 550.0)
    assert (a.status == b.status).all() and a.valid.mean() > 0.9
    np.testing.assert_allclose(b.position_mm[b.valid], a.position_mm[a.valid], atol=1e-9)


def test_an_odd_asphere_loads_from_a_lens_file_and_refuses_both_kinds(tmp_path):
    from conftest import singlet_dict
    from dcdi_core.optics.errors import LensFileError
    from dcdi_core.optics.lens import Lens
    d = singlet_dict(asph=[1e-3])
    d["surface"][1]["odd_aspheric_coefficients"] = [0.0, 1e-3]
    with pytest.raises(LensFileError, match="an even or an odd asphere, not both"):
        Lens.from_dict(d)
    d = singlet_dict()
    d["surface"][1]["odd_aspheric_coefficients"] = [1e-4, 0.0, 1e-5, 0.0]
    lens = Lens.from_dict(d)
    assert lens.surfaces[1].odd_aspheric_coefficients == (1e-4, 0.0, 1e-5)     # trailing zeros dropped
    assert lens.surfaces[1].is_aspheric
    r2 = np.array([0.0, 4.0])
    assert np.allclose(lens.surfaces[1].sag(r2), profile_of(lens.surfaces[1]).sag(r2))
