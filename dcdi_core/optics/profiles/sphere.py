"""A sphere of curvature c = 1/R (1/mm)."""
from __future__ import annotations

import numpy as np

from .base import Profile, check_conic_sheet, conic_root


class Sphere(Profile):
    def __init__(self, c: float):
        self.c = float(c)

    def sag(self, r2):
        r2 = np.asarray(r2, dtype=np.float64)
        c = self.c
        return c * r2 / (1.0 + np.sqrt(np.maximum(1.0 - c * c * r2, 0.0)))

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        return conic_root(self.c, 0.0, xs, ys, dx, dy, dz, kill)

    def check_sheet(self, z_local, kill) -> None:
        check_conic_sheet(self.c, 0.0, z_local, kill)

    def normal(self, xs, ys, z_local, r2, dt):
        c = self.c
        # the implicit normal (-c x, -c y, 1 - c z) of a sphere is unit length already
        return -c * xs, -c * ys, 1.0 - (c * (1.0 + 0.0)) * z_local
