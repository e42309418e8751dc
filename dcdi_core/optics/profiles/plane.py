"""A plane surface (R = inf): the vertex plane itself."""
from __future__ import annotations

import numpy as np

from .base import Profile


class Plane(Profile):
    curved = False

    def sag(self, r2):
        return np.zeros_like(np.asarray(r2, dtype=np.float64))

    def root(self, xs, ys, dx, dy, dz, kill, newton_tol, newton_iter):
        return None

    def normal(self, xs, ys, z_local, r2, dt):
        return dt.type(0.0), dt.type(0.0), dt.type(1.0)
