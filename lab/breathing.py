"""Each lens's breathing and depth-dependent distortion: the chief-ray map
the renderers use against chief rays found without the engine's aiming.

For every catalogue lens, focused at infinity, 5 m and 1.5 m: the focal
length Match Camera to Lens gives a 3:2 frame there
(``camera.framing_focal_length_mm``); how far the sensor's corner (field
0.95 of an object at the focus distance) moves from its place at infinity
focus, in percent and in 100 um pixels, by the map and by a direct trace;
and how far it moves, at one focus, between objects at 1.5 and 6 m (the
depth dependence). The direct trace (:func:`traced_chief_height`) shoots a
fan of rays from the object point across the first vertex plane and takes
the sensor height where the stop height crosses zero: no Newton iteration,
no ray aiming.

Run ``python -m lab breathing [--lenses ID ...]`` (about a minute).
"""
from __future__ import annotations

import math

import numpy as np

PIXEL_MM = 0.1          # the pixel the table's "px" columns count in
FIELD = 0.95            # the corner's field (of the sensor semi-diagonal)


def traced_chief_height(lens, depth_mm: float, p: float) -> float:
    """Sensor height (mm) of the ray from the source (depth_mm, p) through the
    stop's centre, found by tracing fans of rays (no aiming): a coarse fan
    across the first vertex plane, then a fine one around where the height
    at the stop changes sign, interpolated linearly at zero."""
    from dcdi_core.optics.aiming import launch
    from dcdi_core.optics.paraxial import first_order
    from dcdi_core.optics.trace import trace

    wl = lens.wavelength_nm
    z_ep = first_order(lens, wl).entrance_pupil_position_mm
    sd0 = lens.surfaces[0].semi_diameter_mm

    def fan(v):
        o, d = launch(lens, np.full(v.shape, depth_mm), np.full(v.shape, p), np.zeros_like(v), v, z_ep)
        at_stop = trace(lens, o, d, wl, apertures=False, upto_surface=lens.stop_index)
        at_sensor = trace(lens, o, d, wl, apertures=False)
        ok = at_stop.valid & at_sensor.valid
        return v[ok], at_stop.position_mm[ok, 1], at_sensor.position_mm[ok, 1]

    def crossing(v, ys):
        k = np.flatnonzero(np.diff(np.sign(ys)) != 0)
        if k.size == 0:
            raise ValueError(f"{lens.id}: no ray from p = {p:.4g} at {depth_mm:.4g} mm passes the stop's centre")
        return int(k[0])

    v, ys, _ = fan(np.linspace(-2.0 * sd0, 2.0 * sd0, 4001))
    k = crossing(v, ys)
    v, ys, yh = fan(np.linspace(v[k], v[k + 1], 2001))
    j = crossing(v, ys)
    t = ys[j] / (ys[j] - ys[j + 1])
    return float(yh[j] + t * (yh[j + 1] - yh[j]))


def row(lens_id: str) -> dict:
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.optics.paraxial import refocused
    from dcdi_core.render.camera import framing_focal_length_mm, ideal_scale_mm
    from dcdi_core.render.distortion import chief_ray_map

    lens = load_lens(lens_id)
    c = ideal_scale_mm(lens)
    sd = lens.sensor.semi_diagonal_mm
    p = FIELD * sd / c
    out = {"lens": lens_id, "scale_mm": c}
    maps = {f: chief_ray_map(lens, focus_m=f, near_m=0.7) for f in (math.inf, 5.0, 1.5)}
    base_map = float(maps[math.inf].real_from_ideal(p * c, 0.0))
    base_trace = traced_chief_height(refocused(lens, math.inf), math.inf, p)
    for f in (5.0, 1.5):
        d = 1.0 / f
        out[f"framing_{f:g}"] = framing_focal_length_mm(lens, f, 4000, 6000)
        by_map = float(maps[f].real_from_ideal(p * c, d)) - base_map
        by_trace = traced_chief_height(refocused(lens, f), f * 1000.0, p) - base_trace
        out[f"breathing_{f:g}_pct"] = 100.0 * by_map / base_trace
        out[f"breathing_{f:g}_err_px"] = (by_map - by_trace) / PIXEL_MM
    depth_map = float(maps[1.5].real_from_ideal(p * c, 1 / 1.5) - maps[1.5].real_from_ideal(p * c, 1 / 6.0))
    f15 = refocused(lens, 1.5)
    depth_trace = traced_chief_height(f15, 1500.0, p) - traced_chief_height(f15, 6000.0, p)
    out["depth_px"] = depth_map / PIXEL_MM
    out["depth_err_px"] = (depth_map - depth_trace) / PIXEL_MM
    return out


def format_table(rows_: list[dict]) -> str:
    lines = ["| lens | focal length (ideal scale) mm | Match Camera at 5 m / 1.5 m, mm | corner moves, infinity to "
             "5 m / 1.5 m | map - trace, px | corner at 1.5 m focus, object 1.5 vs 6 m, px (map - trace) |",
             "|---|---|---|---|---|---|"]
    for r in rows_:
        lines.append(f"| `{r['lens']}` | {r['scale_mm']:.2f} | {r['framing_5']:.1f} / {r['framing_1.5']:.1f} | "
                     f"{r['breathing_5_pct']:+.2f} % / {r['breathing_1.5_pct']:+.2f} % | "
                     f"{r['breathing_5_err_px']:+.4f} / {r['breathing_1.5_err_px']:+.4f} | "
                     f"{r['depth_px']:+.3f} ({r['depth_err_px']:+.4f}) |")
    return "\n".join(lines)


def picture(path, lens_id: str = "zeiss-sonnar-50mm-f1-5", far_m: float = 10.0, near_m: float = 0.9) -> dict:
    """The built-in synthetic scene (textures from 0.8 m to infinity) through
    ``lens`` wide open with its distortion and breathing (`dcdi bokeh
    --distort`), focused at ``far_m`` and at ``near_m``: three panels, the
    two renders and their overlay (red: focused near; cyan: focused far),
    where a pull of focus shows as colour fringes growing toward the
    corners. Returns the corner's shift in pixels by the chief-ray map."""
    import warnings

    from dcdi_core.io.images import write_image
    from dcdi_core.models.dacn.evaluate import panel_strip
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.render.camera import ideal_scale_mm
    from dcdi_core.render.distortion import chief_ray_map
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.synthetic import synthetic_rgbd

    lens = load_lens(lens_id)
    img, depth = synthetic_rgbd(240, 360)
    geo = ImageGeometry.full_sensor(lens, 240, 360)
    out = {}
    for name, focus in (("far", far_m), ("near", near_m)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[name] = bokeh(img, depth.astype(np.float64), lens,
                              BokehOptions(focus_m=focus, geometry=geo, distortion=True)).image
    lum = {k: np.clip(v @ np.array([0.2126, 0.7152, 0.0722]), 0.0, None) for k, v in out.items()}
    overlay = np.stack([lum["near"], lum["far"], lum["far"]], -1).astype(np.float32)
    write_image(path, panel_strip([out["far"], out["near"], overlay]))
    sd = lens.sensor.semi_diagonal_mm
    shift = {}
    for name, focus in (("far", far_m), ("near", near_m)):
        m = chief_ray_map(lens, focus_m=focus, near_m=0.7)
        shift[name] = float(m.real_from_ideal(0.95 * sd, 1.0 / focus))
    return {"corner_shift_px": (shift["near"] - shift["far"]) / geo.pixel_pitch_mm, "scale_mm": ideal_scale_mm(lens)}


def main(argv=None) -> int:
    import argparse

    from dcdi_core.optics.lens import available_lenses
    ap = argparse.ArgumentParser(prog="python -m lab breathing",
                                 description="each lens's breathing and depth-dependent distortion, the chief-ray "
                                             "map against a direct trace (module docstring)")
    ap.add_argument("--lenses", nargs="+", default=None, help="lens ids (default: every lens)")
    ap.add_argument("--picture", default=None, metavar="PNG",
                    help="also write the Sonnar's pull of focus from 10 m to 0.9 m as a picture (three panels)")
    args = ap.parse_args(argv)
    known = available_lenses()
    lenses = args.lenses or known
    bad = [x for x in lenses if x not in known]
    if bad:
        ap.error(f"--lenses {bad[0]!r}: allowed one of {', '.join(known)}")
    print(format_table([row(x) for x in lenses]))
    print(f"\npx: {PIXEL_MM * 1000:g} um pixels; the corner: field {FIELD:g}; Match Camera: a 3:2 frame")
    if args.picture:
        r = picture(args.picture)
        print(f"{args.picture}: the Sonnar focused at 10 m, at 0.9 m, and their overlay (red: near, cyan: far); "
              f"the corner (field 0.95) moves {r['corner_shift_px']:.1f} px at 360 x 240")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
