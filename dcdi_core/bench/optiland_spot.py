"""The spot work of `dcdi bench trace --optiland` done by Optiland 0.6.3.

Runs under Optiland's own interpreter (.venv-optiland/: Optiland needs
numpy 2), so it imports only optiland, numpy and the standard library,
never dcdi_core. Reads a JSON spec (the file named by argv[1], else stdin):

    surfaces            [{radius_mm (null: plane), conic, thickness_mm (to the next
                        surface or the image plane), semi_diameter_mm, index (of the
                        medium after it, at the wavelength)}], first to last
    stop_index          the aperture stop (0-based)
    object_distance_mm  object plane to the first vertex
    object_index        the object space's index
    field_heights_mm    object heights (y, mm), one spot each
    wavelength_nm       one wavelength (Optiland traces one per call; the
                        constant-index materials hold that wavelength's indices)
    pupil_samples       n: the centres of an n x n grid over the stop inside its
                        rim (dcdi's stop_grid), the same points for every field
    repeat              timed traces after an untimed warm-up (best is kept)

Prints JSON: seconds (the best trace, wall), rays (traced), and per field
valid (rays reaching the image plane), centroid_mm [x, y] and rms_radius_mm
(about the centroid) on the image plane.
"""
import json
import sys
import time

import numpy as np

# Optiland is imported inside the functions: this file ships in the wheel, whose every module must
# import without it (the benchmark runs it under the interpreter of .venv-optiland/)


def stop_grid(n: int):
    """An Optiland distribution of the cell centres of an n x n grid over the
    unit pupil, inside its rim."""
    from optiland.distribution import BaseDistribution

    class StopGrid(BaseDistribution):
        def generate_points(self, num_points: int):
            c = (np.arange(num_points) + 0.5) / num_points * 2.0 - 1.0
            x, y = np.meshgrid(c, c)
            keep = x * x + y * y <= 1.0
            self.x, self.y = x[keep], y[keep]

    grid = StopGrid()
    grid.generate_points(n)
    return grid


def build(spec):
    """The spec's lens as an Optic: constant-index media, physical apertures
    at the semi-diameters, EPD = the stop's diameter (the stop is in front:
    the entrance pupil is the stop itself), object heights as fields."""
    from optiland.materials import IdealMaterial
    from optiland.optic import Optic
    from optiland.physical_apertures import RadialAperture
    optic = Optic()
    optic.surfaces.add(index=0, radius=np.inf, thickness=spec["object_distance_mm"],
                       material=IdealMaterial(spec["object_index"]))
    for i, s in enumerate(spec["surfaces"]):
        optic.surfaces.add(index=i + 1, radius=np.inf if s["radius_mm"] is None else s["radius_mm"],
                           conic=s["conic"], thickness=s["thickness_mm"], material=IdealMaterial(s["index"]),
                           is_stop=i == spec["stop_index"], aperture=RadialAperture(r_max=s["semi_diameter_mm"]))
    optic.surfaces.add(index=len(spec["surfaces"]) + 1)
    optic.set_aperture("EPD", 2.0 * spec["surfaces"][spec["stop_index"]]["semi_diameter_mm"])
    optic.fields.set_type("object_height")
    for h in spec["field_heights_mm"]:
        optic.fields.add(y=h)
    optic.wavelengths.add(value=spec["wavelength_nm"] / 1000.0, is_primary=True)
    return optic


def main(argv) -> int:
    spec = json.loads(open(argv[1]).read() if len(argv) > 1 else sys.stdin.read())
    optic = build(spec)
    h = np.asarray(spec["field_heights_mm"], dtype=np.float64)
    hy = h / max(np.abs(h).max(), 1e-300)
    grid = stop_grid(spec["pupil_samples"])

    def run():
        return optic.trace(np.zeros_like(hy), hy, spec["wavelength_nm"] / 1000.0, distribution=grid, record=False)

    run()
    best = float("inf")
    for _ in range(spec["repeat"]):
        t = time.perf_counter()
        rays = run()
        best = min(best, time.perf_counter() - t)
    n = grid.x.size
    x, y = np.asarray(rays.x).reshape(h.size, n), np.asarray(rays.y).reshape(h.size, n)
    ok = (np.asarray(rays.i).reshape(h.size, n) > 0) & np.isfinite(x) & np.isfinite(y)
    spots = []
    for f in range(h.size):
        xs, ys = x[f, ok[f]], y[f, ok[f]]
        cx, cy = float(xs.mean()), float(ys.mean())
        spots.append({"valid": int(ok[f].sum()), "centroid_mm": [cx, cy],
                      "rms_radius_mm": float(np.sqrt(np.mean((xs - cx) ** 2 + (ys - cy) ** 2)))})
    print(json.dumps({"seconds": best, "rays": int(x.size), "spots": spots}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
