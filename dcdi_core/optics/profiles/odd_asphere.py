"""An odd asphere (Zemax's ODDASPH): the conic (c, k) plus sum_i b_i r^i,
i = 1, 2, 3, ... (b_i in mm^(1 - i)): every power of r, so that a term b_1 r
makes a cone's tip at the vertex. The intersection starts from the conic's
root and is refined by Newton steps in the distance along the ray (the sag
is smooth in r, not in r^2), the normal from dz/dr."""
from __future__ import annotations

import numpy as np

from .base import Profile, check_conic_sheet, conic_root, kill_unsolved


class OddAsphere(Profile):
    def __init__(self, c: float, k: float, coeffs: tuple[float, ...]):
        self.c, self.k, self.coeffs = float(c), float(k), tuple(float(b) for b in coeffs)

    def _sag_and_dr(self, r):
        """(sag z, dz/dr, in the conic's domain) at radial distance r (mm)."""
        c, k = self.c, self.k
        r2 = r * r
        arg = 1.0 - (1.0 + k) * c * c * r2
        dom = arg >= 0.0
        root = np.sqrt(np.maximum(arg, 0.0))
        z = c * r2 / (1.0 + root)
        dz = c * r / np.maximum(root, 1e-12)                   # d/dr of the conic's sag
        power = np.ones_like(r)
        for i, b in enumerate(self.coeffs, start=1):
            dz = dz + i * b * power
            power = power * r
            z = z + b * power
        return z, dz, dom

    def sag(self, r2):
        return self._sag_and_dr(np.sqrt(np.asarray(r2, dtype=np.float64)))[0]

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        t = conic_root(self.c, self.k, xs, ys, dx, dy, dz, kill)
        converged = np.zeros(t.shape, dtype=bool)
        for _ in range(newton_iter):
            x, y = xs + t * dx, ys + t * dy
            r = np.sqrt(x * x + y * y)
            z, dzdr, _ = self._sag_and_dr(r)
            # d r / d t = (x dx + y dy) / r; at the axis the cone's slope acts along the ray's tilt
            drdt = np.where(r > 0, (x * dx + y * dy) / np.where(r > 0, r, 1.0), np.hypot(dx, dy))
            g = t * dz - z
            dg = dz - dzdr * drdt
            dg = np.where(np.abs(dg) < 1e-12, 1e-12, dg)
            step = g / dg
            t = t - np.where(converged, 0.0, step)
            converged |= np.abs(step) < newton_tol
            if converged.all():
                break
        x, y = xs + t * dx, ys + t * dy
        _, _, dom = self._sag_and_dr(np.sqrt(x * x + y * y))
        t = np.where(np.isfinite(t), t, 0.0)
        kill_unsolved(converged, dom, kill)
        return t

    def check_sheet(self, z_local, kill) -> None:
        check_conic_sheet(self.c, self.k, z_local, kill)

    def normal(self, xs, ys, z_local, r2, dt):
        r = np.sqrt(r2)
        _, dzdr, _ = self._sag_and_dr(r)
        inv_r = np.where(r > 0, 1.0 / np.where(r > 0, r, 1.0), 0.0)
        nx, ny = -dzdr * xs * inv_r, -dzdr * ys * inv_r
        nz = 1.0 / np.sqrt(nx * nx + ny * ny + 1.0)
        return (nx * nz).astype(dt, copy=False), (ny * nz).astype(dt, copy=False), nz.astype(dt, copy=False)
