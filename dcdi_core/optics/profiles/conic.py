"""A conic of curvature c (1/mm) and conic constant k (k = -1: a paraboloid)."""
from __future__ import annotations

import numpy as np

from .base import Profile, check_conic_sheet, conic_root


class Conic(Profile):
    def __init__(self, c: float, k: float):
        self.c, self.k = float(c), float(k)

    def sag(self, r2):
        r2 = np.asarray(r2, dtype=np.float64)
        c, k = self.c, self.k
        return c * r2 / (1.0 + np.sqrt(np.maximum(1.0 - (1.0 + k) * c * c * r2, 0.0)))

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        return conic_root(self.c, self.k, xs, ys, dx, dy, dz, kill)

    def check_sheet(self, z_local, kill) -> None:
        check_conic_sheet(self.c, self.k, z_local, kill)

    def normal(self, xs, ys, z_local, r2, dt):
        c, k = self.c, self.k
        nx, ny = -c * xs, -c * ys
        nz = 1.0 - (c * (1.0 + k)) * z_local
        inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
        return nx * inv, ny * inv, nz * inv
