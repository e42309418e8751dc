"""`dcdi bench quality LENS`: the error against run time of each knob of the
PSF work (``psf.budget``: rays, wavelengths, field step) for one lens, and
the planner's choice for each budget, checked by rendering it.

The scene is the built-in synthetic RGB-D (``render.synthetic``: textures
from 0.8 m to infinity, bright lights at 6 m), blurred by ``app.bokeh``
with the lens wide open and focused at 2 m, from the PSF source a planned
job of this lens uses (its ray map, else traced). Every row is one knob
changed from the converged reference (``psf.budget.REFERENCE``), run in
this process with its own PSF cache; PSNR (peak 1) against the reference.
Times are wall seconds of the whole job with the process's CPU seconds
beside them.

    dcdi bench quality zeiss-sonnar-50mm-f1-5 [--size 270 480] [--measure] [--quick]

The knob table printed is the lens's shipped one (``psf/data/quality``,
written by ``python -m lab quality-tables``); ``--measure`` measures it
again here.
"""
from __future__ import annotations

import math
import os
import tempfile
import time

import numpy as np

FOCUS_M = 2.0
SCENE = "the built-in synthetic scene (render.synthetic, seed 0), wide open, focus 2 m"
LEVELS = {"pupil_samples": (16, 24, 32, 48, 64), "n_wavelengths": (3, 5, 9, 15), "field_step_px": (8, 16, 32, 64)}
QUICK_LEVELS = {"pupil_samples": (16, 32), "n_wavelengths": (5,), "field_step_px": (32,)}
# the blur's knobs: the coarse layers' rule (BokehOptions.coarse_blur, px) and the kernels' crop
# (support_eps): their error and the blur's seconds are measured with the cheapest PSF work (the knobs'
# errors are independent), against every layer at full resolution with the reference's crop
BLUR_LEVELS = {"coarse_blur": (16.0, 8.0, 4.0, 2.0), "support_eps": (3e-3, 1e-2, 3e-2)}
CHEAP = {"pupil_samples": 16, "n_wavelengths": 3, "field_step_px": 64}
SIZES = ((270, 480), (540, 960))
BUDGETS_DB = (30.0, 40.0, 50.0, 55.0)


def planned_source(lens) -> str:
    """The source a planned job of ``lens`` is measured with: its ray map where one ships, else traced."""
    from ..shipped import raymap_file
    return "raymap" if raymap_file(lens.id) is not None else "trace"


def render(lens, img, depth, knobs: dict, source: str, focus_m: float = FOCUS_M, seconds: dict | None = None):
    """(image, wall s, CPU s, kernel px) of the bokeh with ``knobs`` (missing
    ones: the reference's); ``seconds``: filled with the job's stages' (PSFs, bokeh)."""
    from .. import app
    from ..psf.budget import REFERENCE
    from ..psf.compute import PSFSettings
    from ..render.request import RenderRequest
    k = {**REFERENCE, **knobs}
    settings = PSFSettings(pupil_samples=int(k["pupil_samples"]), n_wavelengths=int(k["n_wavelengths"]))
    req = app.BokehRequest(img, depth, lens, focus_m=focus_m, render=RenderRequest(lens, psf=settings),
                           coarse_blur=k.get("coarse_blur"), support_eps=k.get("support_eps"),
                           psf=app.PSFRequest(source=source, field_step_px=k["field_step_px"]),
                           image_name="the quality scene")
    with tempfile.TemporaryDirectory() as d:
        old = os.environ.get("DCDI_CACHE_DIR")
        os.environ["DCDI_CACHE_DIR"] = d
        try:
            t, c = time.perf_counter(), time.process_time()
            r = app.bokeh(req)
            wall, cpu = time.perf_counter() - t, time.process_time() - c
            if seconds is not None:
                seconds.update(r.seconds)
        finally:
            if old is None:
                os.environ.pop("DCDI_CACHE_DIR", None)
            else:
                os.environ["DCDI_CACHE_DIR"] = old
    return r.image, wall, cpu, r.source.library.kernel_size


def mse(a, b) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def psnr(m: float) -> float:
    return math.inf if m <= 0 else -10.0 * math.log10(m)


def measure(lens, rows: int, cols: int, levels=None, say=print) -> dict:
    """One size's table row: each knob's levels as [value, squared error, wall s]."""
    import warnings
    from ..psf.compute import KernelTooSmallWarning
    from ..render.geometry import ImageGeometry
    from ..render.synthetic import synthetic_rgbd
    levels = levels or LEVELS
    img, depth = synthetic_rgbd(rows, cols)
    source = planned_source(lens)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        ref, ref_wall, cpu, k = render(lens, img, depth, {}, source)
        say(f"| {lens.id} | {cols} x {rows} | reference | - | converged | {ref_wall:.2f} / {cpu:.2f} | {k} |")
        knobs = {}
        for name, values in levels.items():
            knobs[name] = []
            for v in values:
                im, wall, cpu, k = render(lens, img, depth, {name: v}, source)
                e = mse(im, ref)
                knobs[name].append([v, e, round(wall, 3)])
                say(f"| {lens.id} | {cols} x {rows} | {name} | {v} | {psnr(e):.1f} | {wall:.2f} / {cpu:.2f} | {k} |")
        blur_knobs, blur_s = measure_blur(lens, img, depth, source, say, f"{cols} x {rows}")
        knobs.update(blur_knobs)
    pitch = ImageGeometry.full_sensor(lens, rows, cols).pixel_pitch_mm
    return {"rows": rows, "cols": cols, "pixel_pitch_mm": pitch, "reference_s": round(ref_wall, 3),
            "blur_s": round(blur_s, 3), "knobs": knobs}


def measure_blur(lens, img, depth, source: str, say=print, size: str = "", knobs=None) -> tuple[dict, float]:
    """({blur knob: [[value, squared error (None where the level changed
    nothing: unmeasured), the blur's wall s]]}, the blur's wall s with the
    reference's knobs), with the cheapest PSF work (:data:`CHEAP`) on both
    sides. ``knobs``: which of :data:`BLUR_LEVELS` (default all)."""
    sec: dict = {}
    base = render(lens, img, depth, CHEAP, source, seconds=sec)[0]
    full_s = sec["bokeh"]
    out = {}
    for name in knobs or BLUR_LEVELS:
        out[name] = []
        for v in BLUR_LEVELS[name]:
            sec = {}
            im, wall, cpu, k = render(lens, img, depth, {**CHEAP, name: v}, source, seconds=sec)
            e = mse(im, base)
            # a level that changed nothing here says nothing of its error where it does: not offered (None)
            out[name].append([v, e if e > 0 else None, round(sec["bokeh"], 3)])
            say(f"| {lens.id} | {size} | {name} | {v:g} | {'no effect' if e == 0 else f'{psnr(e):.1f}'} | "
                f"{sec['bokeh']:.2f} (blur; {full_s:.2f} with the reference's) | {k} |")
    return out, full_s


def table(lens, sizes=SIZES, levels=None, say=print) -> dict:
    """The lens's whole table (``psf.budget``'s format)."""
    from ..optics.lens import lens_fingerprint
    from ..psf.budget import FORMAT, FORMAT_VERSION, REFERENCE
    stop = lens.surfaces[lens.stop_index].semi_diameter_mm
    return {"format": FORMAT, "version": FORMAT_VERSION, "lens_id": lens.id, "lens_fingerprint": lens_fingerprint(lens),
            "stop_semi_diameter_mm": stop, "scene": SCENE, "source": planned_source(lens), "reference": REFERENCE,
            "sizes": [measure(lens, r, c, levels, say) for r, c in sizes]}


def check_plans(lens, rows: int, cols: int, budgets=BUDGETS_DB, focus_m: float = FOCUS_M, folder=None,
                say=print) -> list[dict]:
    """Each budget's plan at this size, rendered and measured against the reference: [{budget, plan, PSNR, s}]."""
    import warnings
    from ..psf.budget import plan
    from ..psf.compute import KernelTooSmallWarning
    from ..render.geometry import ImageGeometry
    from ..render.synthetic import synthetic_rgbd
    img, depth = synthetic_rgbd(rows, cols)
    source = planned_source(lens)
    pitch = ImageGeometry.full_sensor(lens, rows, cols).pixel_pitch_mm
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        ref, ref_wall, _, _ = render(lens, img, depth, {}, source, focus_m)
        full, full_wall, _, _ = render(lens, img, depth, {"pupil_samples": 64}, source, focus_m)
        say(f"| {lens.id} | {cols} x {rows} | focus {focus_m:g} m | full quality (64 rays, 31 wavelengths, full grid) "
            f"| - | {psnr(mse(full, ref)):.1f} | {full_wall:.2f} |")
        from ..app.render import widest_blur_px
        blur = widest_blur_px(lens, pitch, focus_m, depth)       # the job's floor of rays, as app.bokeh plans
        for b in budgets:
            p = plan(lens, pitch, b, folder=folder, blur_px=blur)
            im, wall, cpu, _ = render(lens, img, depth, {"pupil_samples": p.pupil_samples,
                                                         "n_wavelengths": p.n_wavelengths,
                                                         "field_step_px": p.field_step_px,
                                                         "coarse_blur": p.coarse_blur,
                                                         "support_eps": p.support_eps}, source, focus_m)
            got = psnr(mse(im, ref))
            exp = "-" if p.expected_db is None else f"{p.expected_db:.1f}"
            coarse = ("" if p.coarse_blur is None else f", coarse layers {p.coarse_blur:g}") + \
                ("" if p.support_eps == 1e-3 else f", kernel crop {p.support_eps:g}")
            say(f"| {lens.id} | {cols} x {rows} | focus {focus_m:g} m | {b:g} dB: {p.pupil_samples} rays, "
                f"{p.n_wavelengths} wavelengths, field step {p.field_step_px or 'full'}{coarse} | {exp} | {got:.1f} "
                f"| {wall:.2f} |")
            out.append({"budget_db": b, "plan": p, "psnr_db": got, "wall_s": wall, "full_wall_s": full_wall})
    return out


def print_row(lens_id: str, row: dict) -> None:
    """A measured size's rows of the knob table (``measure``'s, or a shipped table's)."""
    size = f"{row['cols']} x {row['rows']}"
    print(f"| {lens_id} | {size} | reference (96 rays, 31 wavelengths, full grid) | - | converged | "
          f"{row['reference_s']:.2f} |")
    for name, levels in row["knobs"].items():
        for v, e, s in levels:
            db = "no effect" if e is None else f"{psnr(e):.1f}"
            what = f"{s:.2f} (blur; {row['blur_s']:.2f} with the reference's)" if name in BLUR_LEVELS else f"{s:.2f}"
            print(f"| {lens_id} | {size} | {name} | {v} | {db} | {what} |")


def bench_quality(lens_id: str | None, quick: bool = False, sizes=None, measure_again: bool = False) -> int:
    """Print the lens's knob table (its shipped one; measured here with
    ``measure_again``, ``quick`` or where none ships) and render the planner's
    choice for each budget against the converged render."""
    from ..errors import InputRangeError
    from ..optics.lens import load_lens
    from ..psf.budget import load_table
    if not lens_id:
        raise InputRangeError("lens", None, "a lens id or .toml path: dcdi bench quality LENS")
    lens = load_lens(lens_id)
    table = None if (quick or measure_again) else load_table(lens.id)
    if sizes is None:
        sizes = ((45, 80),) if quick else tuple((r["rows"], r["cols"]) for r in table["sizes"]) if table else SIZES
    print(f"dcdi bench quality {lens.id}: each knob alone against the converged render (96 x 96 rays, 31 "
          f"wavelengths, the full field grid) on {SCENE}; PSNR dB; wall s of the whole job (the coarse rule: of "
          "the blur, with the cheapest PSFs on both sides)"
          + (f"; from its shipped table ({table['source']})" if table else "; measured now"))
    print("| lens | image | knob | value | PSNR dB | wall s |")
    print("|---|---|---|---|---|---|")
    if table:
        for row in table["sizes"]:
            print_row(lens.id, row)
    else:
        for r, c in sizes:
            print_row(lens.id, measure(lens, r, c, QUICK_LEVELS if quick else LEVELS, say=lambda _: None))
    print()
    print(f"The planner's choice for each budget ({lens.id}'s shipped error table), rendered now beside the "
          "converged render and the full-quality defaults; wall s of the whole job")
    print("| lens | image | scene | budget: plan | expected dB | measured dB | wall s |")
    print("|---|---|---|---|---|---|---|")
    for r, c in sizes:
        for focus in ((FOCUS_M,) if quick else (FOCUS_M, 1.2)):
            check_plans(lens, r, c, (30.0,) if quick else BUDGETS_DB, focus)
    return 0


__all__ = ["bench_quality", "measure", "measure_blur", "table", "check_plans", "render", "LEVELS", "BLUR_LEVELS", "SIZES", "BUDGETS_DB"]
