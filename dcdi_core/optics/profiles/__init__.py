"""Surface kinds, one class per kind, each owning its sag, its ray
intersection and its normal, vectorised over rays (the tracer,
``optics.trace``, loops over a lens's surfaces calling them).

A surface is described in its local frame (vertex at the origin, axis +z);
lengths in mm, curvature c = 1/R in 1/mm. A new kind is one new module with
one :class:`~.base.Profile` subclass, and a line in :func:`profile_of`.

| kind | module | sag z(r) |
| --- | --- | --- |
| :class:`Plane` | ``plane.py`` | 0 |
| :class:`Sphere` | ``sphere.py`` | c r^2 / (1 + sqrt(1 - c^2 r^2)) |
| :class:`Conic` | ``conic.py`` | c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) |
| :class:`EvenAsphere` | ``even_asphere.py`` | the conic + sum_i a_i r^(2 i) |
| :class:`OddAsphere` | ``odd_asphere.py`` | the conic + sum_i b_i r^i |
"""
from __future__ import annotations

from .base import Profile
from .conic import Conic
from .even_asphere import EvenAsphere
from .odd_asphere import OddAsphere
from .plane import Plane
from .sphere import Sphere


def profile_of(surface) -> Profile:
    """The kind of an ``optics.surfaces.Surface`` (its curvature, conic and
    even aspheric coefficients)."""
    c, k = surface.curvature, float(surface.conic)
    coeffs = tuple(float(a) for a in surface.aspheric_coefficients)
    odd = tuple(float(b) for b in getattr(surface, "odd_aspheric_coefficients", ()))
    if odd:
        return OddAsphere(c, k, odd)
    if coeffs:
        return EvenAsphere(c, k, coeffs)
    if c == 0.0:
        return Plane()
    if k == 0.0:
        return Sphere(c)
    return Conic(c, k)


__all__ = ["Profile", "Plane", "Sphere", "Conic", "EvenAsphere", "OddAsphere", "profile_of"]
