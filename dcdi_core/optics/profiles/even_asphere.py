"""An even asphere: the conic (c, k) plus sum_i a_i r^(2 i), i = 1, 2, ...
(a_i in mm^(1 - 2 i)). The intersection starts from the conic's root and is
refined by a bounded number of Newton steps (rays that do not converge are
killed as NOT_CONVERGED, those that leave the sag's domain as MISSED)."""
from __future__ import annotations

import numpy as np

from .. import surfaces as S
from .base import Profile, check_conic_sheet, conic_root, kill_unsolved


class EvenAsphere(Profile):
    def __init__(self, c: float, k: float, coeffs: tuple[float, ...]):
        self.c, self.k, self.coeffs = float(c), float(k), tuple(float(a) for a in coeffs)

    def sag(self, r2):
        return S.sag_and_slope(self.c, self.k, self.coeffs, np.asarray(r2, dtype=np.float64))[0]

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        t1 = conic_root(self.c, self.k, xs, ys, dx, dy, dz, kill)
        t1, conv, dom = _newton(self.c, self.k, self.coeffs, xs, ys, dx, dy, dz, t1, newton_tol, newton_iter)
        kill_unsolved(conv, dom, kill)
        return t1

    def check_sheet(self, z_local, kill) -> None:
        check_conic_sheet(self.c, self.k, z_local, kill)

    def normal(self, xs, ys, z_local, r2, dt):
        _, slope, _ = S.sag_and_slope(self.c, self.k, self.coeffs, r2)
        nx, ny = -2.0 * slope * xs, -2.0 * slope * ys
        nz = 1.0 / np.sqrt(nx * nx + ny * ny + 1.0)
        return nx * nz, ny * nz, nz


def _newton(c, k, coeffs, x0, y0, dx, dy, dz, t, tol, max_iter):
    """Refine the distance t from the vertex plane: g(t) = t dz - sag(r2(t))
    = 0, at most ``max_iter`` Newton steps. Returns (t, converged, in_domain)."""
    converged = np.zeros(t.shape, dtype=bool)
    for _ in range(max_iter):
        xs = x0 + t * dx
        ys = y0 + t * dy
        r2 = xs * xs + ys * ys
        z, slope, dom = S.sag_and_slope(c, k, coeffs, r2)
        g = t * dz - z
        dg = dz - 2.0 * slope * (xs * dx + ys * dy)
        dg = np.where(np.abs(dg) < 1e-12, 1e-12, dg)
        step = g / dg
        t = t - np.where(converged, 0.0, step)
        converged |= np.abs(step) < tol
        if converged.all():
            break
    xs = x0 + t * dx
    ys = y0 + t * dy
    _, _, dom = S.sag_and_slope(c, k, coeffs, xs * xs + ys * ys)
    t = np.where(np.isfinite(t), t, 0.0)
    return t, converged, dom
