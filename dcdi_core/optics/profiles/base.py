"""What every surface kind provides to the tracer (``optics.trace``).

The tracer moves each ray to the surface's vertex plane first (position xs,
ys there, direction dx, dy, dz), then asks the kind for:

- ``root``: the distance t1 along the ray from the vertex plane to the
  surface (None for a plane: the vertex plane is the surface), marking with
  ``kill(mask, code)`` the rays that miss it;
- ``check_sheet``: rays whose root lies on the other sheet of the conic
  (the one without the vertex) are killed;
- ``normal``: the unit normal at the hit (local z ``z_local``, r^2 ``r2``),
  oriented along +z at the vertex.

The intersection is written after Spencer & Murty (JOSA 52, 1962) and
rayoptics: the quadratic of the conic is solved in the form
-C / (B + sign(B) sqrt(B^2 - A C)), which has no cancellation and tends to
the plane's solution as c -> 0.
"""
from __future__ import annotations

import numpy as np

from .. import surfaces as S


class Profile:
    """A surface kind (subclasses: plane, sphere, conic, even asphere)."""

    curved = True

    def sag(self, r2):
        """Sag z (mm) at squared radial distance r2 (mm^2)."""
        raise NotImplementedError

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        """t1 (mm) from the vertex plane along the ray to the surface, or None."""
        raise NotImplementedError

    def check_sheet(self, z_local, kill) -> None:
        """Kill the rays whose root lies on the sheet without the vertex."""

    def normal(self, xs, ys, z_local, r2, dt):
        """(nx, ny, nz): the unit normal at the hit, along +z at the vertex."""
        raise NotImplementedError


def conic_root(c, k, xs, ys, dx, dy, dz, kill):
    """The conic's root t1 from the vertex plane (misses killed as MISSED)."""
    dt = xs.dtype
    A = c * (1.0 + k * dz * dz) if k != 0.0 else dt.type(c)
    B = c * (xs * dx + ys * dy) - dz
    C = c * (xs * xs + ys * ys)
    disc = B * B - A * C
    den = B + np.copysign(np.sqrt(np.abs(disc)), B)
    if disc.min() < 0.0 or np.abs(den).min() == 0.0:
        miss = (disc < 0.0) | (den == 0.0)
        den[miss] = 1.0
        t1 = -C / den
        t1[miss] = 0.0
        kill(miss, S.MISSED)
        return t1
    return -C / den


def check_conic_sheet(c, k, z_local, kill) -> None:
    """The root must lie on the sheet that holds the vertex: c (1 + k) z < 1."""
    ck = c * (1.0 + k)
    if (ck > 0 and z_local.max() * ck >= 1.0) or (ck < 0 and z_local.min() * ck >= 1.0):
        kill(ck * z_local >= 1.0, S.MISSED)


def kill_unsolved(converged, in_domain, kill) -> None:
    """After a Newton refinement: rays that left the sag's domain missed the
    surface (MISSED), the others that did not converge NOT_CONVERGED."""
    if not (converged.all() and in_domain.all()):
        kill(~in_domain, S.MISSED)
        kill(~converged, S.NOT_CONVERGED)
