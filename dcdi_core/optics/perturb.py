"""Domain randomisation of a lens: its prescription perturbed at random.

The paper trains its correction network on lenses whose MOS parameters are
perturbed within +-10 %, so that it tolerates manufacturing errors. Each
selected value v becomes v (1 + u), u ~ Uniform(-fraction, +fraction), from
``np.random.default_rng(seed)``.

The draws do not depend on what is selected: the generator always draws a
table u of shape (number of surfaces, 5), columns radius, thickness,
semi-diameter, (nd - 1), vd, in that order, and each selected value uses its
cell. So the radii of ``perturb_lens(lens, seed=7)`` and of
``perturb_lens(lens, seed=7, semi_diameters=True)`` are the same.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..errors import InputRangeError

from .errors import OpticsError
from .lens import Lens
from .materials import ModelGlass

_COLUMNS = ("radius_mm", "thickness_mm", "semi_diameter_mm", "material.nd", "material.vd")


def perturb_lens(lens: Lens, *, seed: int, fraction: float = 0.10, radii: bool = True,
                 thicknesses: bool = True, semi_diameters: bool = False,
                 model_glass: bool = False, refocus: bool = False) -> tuple[Lens, dict]:
    """A randomly perturbed copy of ``lens`` and the record of what changed.

    radii: every finite, non-zero radius (mm) scaled (plane surfaces stay
    plane; conic and aspheric coefficients are left alone). thicknesses:
    every axial thickness (mm), the last one (to the sensor) included.
    semi_diameters: every semi-diameter (mm), the stop's included (otherwise
    none changes, so the F-number's stop stays as designed). model_glass:
    for ``{nd, vd}`` model glasses, nd - 1 and vd scaled (catalogue glasses
    are never changed). refocus: then the sensor is moved (the last
    thickness set) so that the perturbed lens's paraxial focus is the
    nominal lens's, as tolerance analysis does with a focus compensator:
    without it a perturbed thickness to the sensor defocuses the lens by
    far more than the other errors blur it (MOS-S2, +-10 %: on-axis RMS
    blur 4-51 px at 12.2 um over eight draws, the nominal lens 5-10 px;
    refocused 4.4-13.9 px, with the nominal trend over depth).

    Returns ``(lens, record)`` with record = ``{"lens": id, "seed", "fraction",
    "selected": {...}, "changes": [{"surface": 1-based, "field", "from",
    "to"}, ...]}``, JSON-ready. Raises OpticsError naming the surface and the
    seed when a perturbed surface's semi-diameter no longer fits on its
    sphere / conic (draw another seed), InputRangeError for a fraction
    outside [0, 0.5] or a seed that is not an integer >= 0."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputRangeError("seed", seed, "an integer >= 0")
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float, np.integer, np.floating)) \
            or not math.isfinite(fraction) or not (0.0 <= fraction <= 0.5):
        raise InputRangeError("fraction", fraction, "a number in [0, 0.5] (0.1 = +-10 %)")
    fraction = float(fraction)
    seed = int(seed)
    rng = np.random.default_rng(seed)
    u = rng.uniform(-fraction, fraction, size=(len(lens.surfaces), len(_COLUMNS)))
    scale = 1.0 + u
    changes: list[dict] = []

    def note(i, col, old, new):
        changes.append({"surface": i + 1, "field": _COLUMNS[col], "from": float(old), "to": float(new)})

    surfaces = []
    for i, s in enumerate(lens.surfaces):
        kw = {}
        if radii and math.isfinite(s.radius_mm) and s.radius_mm != 0.0:
            kw["radius_mm"] = s.radius_mm * scale[i, 0]
            note(i, 0, s.radius_mm, kw["radius_mm"])
        if thicknesses and s.thickness_mm != 0.0:
            kw["thickness_mm"] = s.thickness_mm * scale[i, 1]
            note(i, 1, s.thickness_mm, kw["thickness_mm"])
        if semi_diameters:
            kw["semi_diameter_mm"] = s.semi_diameter_mm * scale[i, 2]
            note(i, 2, s.semi_diameter_mm, kw["semi_diameter_mm"])
        if model_glass and isinstance(s.material, ModelGlass) and (u[i, 3] != 0.0 or u[i, 4] != 0.0):
            nd, vd = s.material.nd, s.material.vd
            nd2, vd2 = 1.0 + (nd - 1.0) * scale[i, 3], vd * scale[i, 4]
            kw["material"] = ModelGlass(nd2, vd2)
            note(i, 3, nd, nd2)
            note(i, 4, vd, vd2)
        s2 = replace(s, **kw) if kw else s
        c = s2.curvature
        # the same sag-domain rule the prescription loader applies
        if c != 0.0 and not s2.is_aspheric \
                and (1.0 + s2.conic) * c * c * s2.semi_diameter_mm ** 2 > 1.0:
            raise OpticsError(
                f"perturb_lens({lens.id}, seed={seed}, fraction={fraction}): surface {i + 1}: the semi-diameter "
                f"{s2.semi_diameter_mm:.6g} mm no longer fits on the perturbed surface (radius "
                f"{s2.radius_mm:.6g} mm, conic {s2.conic:g}); draw another seed")
        surfaces.append(s2)
    out = lens.with_surfaces(surfaces)
    if refocus:
        from .paraxial import prescribed_focus_diopters, refocused_at_diopters
        sensor_before = out.surfaces[-1].thickness_mm
        out = refocused_at_diopters(out, prescribed_focus_diopters(lens))
        changes.append({"surface": len(surfaces), "field": "thickness_mm (refocused)", "from": float(sensor_before),
                        "to": float(out.surfaces[-1].thickness_mm)})
    record = {
        "lens": lens.id, "seed": seed, "fraction": fraction,
        "selected": {"radii": bool(radii), "thicknesses": bool(thicknesses),
                     "semi_diameters": bool(semi_diameters), "model_glass": bool(model_glass)},
        "refocused": bool(refocus),
        "changes": changes,
    }
    return out, record
