"""Refracting surfaces: sphere, plane, conic and even asphere.

A surface is described in its local frame (vertex at the origin, axis +z):

    z(r) = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum_i a_i r^(2 i),   i = 1, 2, ...

with curvature c = 1/R (1/mm; 0 for a plane), conic constant k and even
aspheric coefficients a_i (mm^(1 - 2 i)). All lengths in millimetres.

How a ray meets each kind of surface (its root, normal, sheet) is the
kind's own class in ``optics.profiles``, one module per kind; this module
holds the prescription's ``Surface``, the ray status codes and the sag
arithmetic the kinds share (:func:`sag_and_slope`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .materials import Material

# Ray status codes; a ray keeps the first reason it died for.
OK = 0
MISSED = 1          # no intersection with the surface sheet that holds the vertex
VIGNETTED = 2       # outside the surface's semi-diameter
TIR = 3             # total internal reflection
NOT_CONVERGED = 4   # Newton refinement on an asphere did not converge
BACKWARD = 5        # the surface lies behind the ray, or the ray does not travel forward (+z)
AIM_FAILED = 6      # ray aiming found no real chief ray for this field / depth

STATUS_NAMES = {
    OK: "ok",
    MISSED: "missed surface",
    VIGNETTED: "vignetted (outside semi-diameter)",
    TIR: "total internal reflection",
    NOT_CONVERGED: "asphere intersection not converged",
    BACKWARD: "travelling backwards / surface behind the ray",
    AIM_FAILED: "ray aiming failed (no real chief ray)",
}

# A ray whose z direction cosine is below this cannot reach a plane a finite
# distance ahead without overflowing: it is treated as not travelling forward.
MIN_FORWARD_COSINE = 1e-9


@dataclass(frozen=True)
class Surface:
    """One refracting surface of a sequential lens.

    ``material`` is the medium after the surface; ``thickness_mm`` the axial
    distance from this vertex to the next vertex (or to the sensor).
    """

    radius_mm: float
    thickness_mm: float
    material: Material
    semi_diameter_mm: float
    conic: float = 0.0
    aspheric_coefficients: tuple[float, ...] = field(default_factory=tuple)
    stop: bool = False
    label: str = ""
    # an odd asphere's terms b_i r^i, i = 1, 2, ... (mm^(1 - i)), added to the sag
    odd_aspheric_coefficients: tuple[float, ...] = field(default_factory=tuple)
    # the iris (the stop only): 0 round, n >= 5 a regular n-gon inscribed in the
    # semi-diameter's circle, a corner at blade_rotation_deg from +y towards +x
    blades: int = 0
    blade_rotation_deg: float = 0.0

    @property
    def curvature(self) -> float:
        """Vertex curvature c = 1/R in 1/mm (0 for a plane, R = inf or 0)."""
        if self.radius_mm == 0 or math.isinf(self.radius_mm):
            return 0.0
        return 1.0 / self.radius_mm

    @property
    def is_aspheric(self) -> bool:
        return any(a != 0.0 for a in self.aspheric_coefficients + self.odd_aspheric_coefficients)

    @property
    def is_plane(self) -> bool:
        return self.curvature == 0.0 and not self.is_aspheric

    def sag(self, r2):
        """Sag z (mm) at squared radial distance r2 (mm^2); NaN-free: r2 beyond
        the conic's domain gives the sag at the domain edge (callers mask it)."""
        r2 = np.asarray(r2, dtype=np.float64)
        c, k = self.curvature, self.conic
        root = np.sqrt(np.maximum(1.0 - (1.0 + k) * c * c * r2, 0.0))
        z = c * r2 / (1.0 + root)
        power = r2
        for a in self.aspheric_coefficients:
            z = z + a * power
            power = power * r2
        if self.odd_aspheric_coefficients:
            r = np.sqrt(r2)
            power = r
            for b in self.odd_aspheric_coefficients:
                z = z + b * power
                power = power * r
        return z

    def max_abs_sag(self) -> float:
        """Largest |sag| over the clear aperture (mm), sampled finely."""
        r2 = np.linspace(0.0, self.semi_diameter_mm ** 2, 257)
        return float(np.max(np.abs(self.sag(r2))))


def sag_and_slope(c, k, coeffs, r2):
    """Sag z(r2) and dz/d(r2) of a conic + even asphere, arrays of r2 (mm^2).

    Returns (z, dzdr2, domain_ok) where domain_ok is False where
    1 - (1+k) c^2 r^2 < 0 (the conic is not defined there)."""
    arg = 1.0 - (1.0 + k) * (c * c) * r2
    domain_ok = arg >= 0.0
    root = np.sqrt(np.maximum(arg, 0.0))
    z = c * r2 / (1.0 + root)
    # dz/d(r2) = c / (2 sqrt(arg)); bounded where arg -> 0 by the domain mask
    dz = c / (2.0 * np.maximum(root, 1e-12))
    if coeffs:
        power = np.ones_like(r2)
        for i, a in enumerate(coeffs, start=1):
            dz = dz + i * a * power
            power = power * r2
            z = z + a * power
    return z, dz, domain_ok
