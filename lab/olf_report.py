"""`python -m lab report olf`: the Omni-Lens-Field's error against its size, time and storage.

For each OLF file (default: the shipped ones) and each of its lenses:

- its held-out figures as the file records them (points traced from another
  seed than the training points, never trained on; the stored weights,
  served by the numpy runtime): PSNR on the paper's scale (peak-normalised,
  8-bit), PSNR of the sum-normalised kernels, SSIM (8-bit) and relative L1
  (the metric of `python -m lab report psf-accuracy`);
- the same figures on fresh points traced now, for the OLF and, beside it,
  for the traced PSF library it learned from, interpolated at those points
  (linear in field and inverse depth: what the renderer uses today); the
  library's errors from `python -m lab report psf-accuracy` are quoted beside them;
- storage, parameters, training minutes;
- the time of a 1280 x 1920 PSF map (16-px patches) of the built-in
  synthetic scene's depth: the traced library's path (library in memory),
  the OLF-backed library's (network included), the network's part alone,
  and the network run once per patch (the paper's way);
- downstream: a simulation and a bokeh of the synthetic scene with the OLF's
  PSFs against the same with the traced library's (image PSNR);
- pixel pitches coarser than the learned one (``pitch_resampling``): the
  OLF's kernels area-resampled, and traced kernels resampled the same way,
  against kernels traced at that pitch (``--pitch-only``: this alone);
- ``--held-out-points RUN/points.npz``: every file scored on the held-out
  points of one training run (per lens and focus band), so two files (an
  old and a new OLF) are compared on the same traced points; a file that
  learned a lens at its prescribed focus only is scored on that focus's
  points.

A sweep file (``--sweep``, JSON lines written by the sweep that chose the
shipped configuration) adds its rows to the table, and every point goes on
a plot of error against storage with the paper's (49.29 dB, 240 MB).
Numpy only: the OLF is served by the runtime.
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np

from dcdi_core.atomic import save_figure, write_text
from . import write_report
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.models.common.metrics import psf_scores
from dcdi_core.psf.sources import OLFLibrary, shipped_olf_files
from dcdi_core.psf.olf import OmniLensField

PAPER_POINT = {"psnr_8bit": 49.29, "ssim_8bit": 0.9953, "megabytes": 240.0, "label": "paper (4 lenses, GPU)"}
# `python -m lab report psf-accuracy mos-s1` (docs/psf.md),
# at the defaults: relative L1 of the library's interpolation between depth
# bins (20) and fields (64), each against directly traced PSFs with the same
# rays (so both include the kernels' ray noise), and the sampling error of
# 64^2 rays x 31 wavelengths against a 512^2-ray reference
LIBRARY_ERRORS = {"interpolation_depth": 0.0094, "interpolation_field": 0.015, "sampling": 0.020}
REPORT_SEED = 20261201


def _settings(entry: dict) -> PSFSettings:
    s = dict(entry["psf_settings"])
    s["band_nm"] = tuple(s["band_nm"])
    return PSFSettings(**s)


def traced_library(entry: dict, lens) -> tuple[PSFLibrary, float]:
    """The traced library the OLF learned ``lens`` from (the cache, or built
    now: the seconds it took, 0 from the cache), at the OLF's kernel size
    (centred crop, renormalised, as the OLF's targets were)."""
    from dataclasses import replace
    from dcdi_core.models.olf.data import crop_normalise
    s = _settings(entry)
    grid = LibraryGrid(**entry["library_grid"])
    t = time.perf_counter()
    lib = PSFLibrary.open(lens, s, grid)
    built = lib.build()
    seconds = time.perf_counter() - t if built else 0.0
    k = int(entry["kernel_size"])
    if lib.kernel_size == k:
        return lib, seconds
    small = PSFLibrary(lens, replace(s, kernel_size=k), grid, None)
    small.psf[...] = crop_normalise(lib.psf, k)
    for name in PSFLibrary.ARRAYS:
        if name not in ("psf", "kernel_size_needed", "energy_outside"):
            getattr(small, name)[...] = getattr(lib, name)
    return small, seconds        # every bin computed: it never traces


def fresh_points(entry: dict, lens, n: int, seed: int):
    """``n`` (field, depth) points drawn as the held-out ones are (uniform in
    field and diopters, a tenth at infinity) and traced now: (field, depth,
    PSFs (n', 3, k, k) summing to 1) for those that hold energy."""
    from dcdi_core.models.olf.data import INFINITY_FRACTION, crop_normalise, trace_points
    rng = np.random.default_rng(seed)
    near, far = entry["depth_range_m"]
    f = rng.uniform(0.0, 1.0, n)
    dio = rng.uniform(1.0 / far, 1.0 / near, n)
    d = np.where(rng.uniform(size=n) < INFINITY_FRACTION, math.inf, 1.0 / dio)
    psf, ok = trace_points(lens, _settings(entry), f, d)
    return f[ok], d[ok], crop_normalise(psf[ok], int(entry["kernel_size"]))


def lens_figures(olf: OmniLensField, lens, n_points: int, seed: int, log) -> dict:
    """Fresh-point figures of the OLF and of the traced library it learned from."""
    entry = olf.lens_entry(lens.id)
    t = time.perf_counter()
    f, d, ref = fresh_points(entry, lens, n_points, seed)
    t_trace = time.perf_counter() - t
    pred = olf.psf(lens, f, d, dtype=np.float64)
    lib, t_lib = traced_library(entry, lens)
    libp = lib.at(f, d)
    log(f"  {lens.id}: {len(f)} fresh points traced in {t_trace:.1f} s; library "
        + (f"built in {t_lib:.1f} s" if t_lib else "from the cache"))
    return {"points": int(len(f)), "olf": psf_scores(pred, ref, scale="sum"),
            "library": psf_scores(libp, ref, scale="sum"), "library_built_s": t_lib}


def map_times(olf: OmniLensField, lens, height: int, width: int, log, repeat: int = 2) -> dict:
    """Seconds of a PSF map of the synthetic scene's depth (height x width at
    the lens's learned pixel pitch): traced library (in memory), OLF-backed
    library (network included), the network's part, the network per patch."""
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.psfmap import patch_inverse_depth, psf_map
    from dcdi_core.render.synthetic import synthetic_rgbd
    entry = olf.lens_entry(lens.id)
    geom = ImageGeometry.from_pixel_pitch(lens, height, width, float(entry["pixel_pitch_mm"]))
    _, depth = synthetic_rgbd(height, width, seed=0)
    depth = depth.astype(np.float64)
    grid = LibraryGrid(**entry["library_grid"])
    lib, _ = traced_library(entry, lens)
    times = {"library": math.inf, "olf": math.inf, "network": math.inf}
    for _ in range(repeat):
        t = time.perf_counter()
        psf_map(lib, geom, depth)
        times["library"] = min(times["library"], time.perf_counter() - t)
        olib = OLFLibrary(olf, lens, grid)
        t = time.perf_counter()
        pm = psf_map(olib, geom, depth)
        times["olf"] = min(times["olf"], time.perf_counter() - t)
        times["network"] = min(times["network"], olib.last_network_s)
    # the paper's way: the network once per patch (field, depth)
    m = 16
    inv, has = patch_inverse_depth(depth, m, grid.far_m)
    d = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), math.inf)
    d = np.maximum(d[has], grid.near_m)
    fields = np.minimum(pm.field[has], 1.0)
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        olf.psf(lens, fields, d)
        best = min(best, time.perf_counter() - t)
    times["network_per_patch"] = best
    times["patches"] = int(has.sum())
    times["bins"] = int(olib.computed.sum())
    times["image"] = [height, width]
    log(f"  {lens.id} PSF map {height} x {width}: library {times['library']:.3f} s, OLF {times['olf']:.3f} s "
        f"(network {times['network'] * 1e3:.1f} ms for {times['bins']} bins x {len(olib.fields)} fields; "
        f"per patch {best * 1e3:.1f} ms for {times['patches']} patches)")
    return times


# the points of the pixel-pitch measurement: fields x depths (m), a few of each
PITCH_FIELDS = (0.0, 0.3, 0.6, 0.9)
PITCH_DEPTHS_M = (0.8, 1.5, 4.0, math.inf)


def pitch_targets(lens, learned_mm: float) -> list[tuple[str, float]]:
    """(label, pixel pitch mm) of the coarser pitches measured: 1.5 and 3 (an
    odd integer: new pixel edges on old ones) times the learned pitch, and
    the pitches of a 480 x 640 and a 180 x 320 image spanning the sensor's
    diagonal (``ImageGeometry.full_sensor``; 180 x 320 is the add-on's
    default preview of a 16:9 render)."""
    from dcdi_core.render.geometry import ImageGeometry
    return [("1.5 x", 1.5 * learned_mm),
            ("480 x 640 full sensor", ImageGeometry.full_sensor(lens, 480, 640).pixel_pitch_mm),
            ("3 x", 3.0 * learned_mm),
            ("180 x 320 full sensor", ImageGeometry.full_sensor(lens, 180, 320).pixel_pitch_mm)]


def pitch_resampling(olf: OmniLensField, lens, log, targets=None) -> list[dict]:
    """At pitches coarser than the learned one (``pitch_targets``): the OLF's
    kernels area-resampled (a) and kernels traced at the learned pitch,
    resampled the same way (b), each against kernels traced directly at the
    new pitch (c) with the same rays (sum-normalised; relative L1, PSNR).
    (b) is the resampling's own error, (a) adds the network's. Points:
    ``PITCH_FIELDS`` x ``PITCH_DEPTHS_M``, the OLF's learned PSF settings."""
    from dataclasses import replace
    from dcdi_core.psf.pitch import area_resample, resampled_size
    from dcdi_core.models.olf.data import crop_normalise, trace_points
    entry = olf.lens_entry(lens.id)
    p0, k = float(entry["pixel_pitch_mm"]), int(entry["kernel_size"])
    s = replace(_settings(entry), kernel_size=k)
    f, d = (a.ravel() for a in np.meshgrid(PITCH_FIELDS, PITCH_DEPTHS_M, indexing="ij"))
    t = time.perf_counter()
    traced0, ok0 = trace_points(lens, s, f, d)
    net = olf.psf(lens, f, d, dtype=np.float64)
    rows = [{"label": "learned", "pitch_mm": p0, "ratio": 1.0, "kernel_size": k, "points": int(ok0.sum()),
             "olf": psf_scores(net[ok0], crop_normalise(traced0[ok0], k), scale="sum"), "traced": None}]
    traced0 = crop_normalise(traced0, k).astype(np.float64)
    for label, p in (targets or pitch_targets(lens, p0)):
        k2 = resampled_size(k, p0, p)
        direct, ok = trace_points(lens, replace(s, pixel_pitch_mm=p, kernel_size=k2), f, d)
        ok = ok & ok0
        ref = crop_normalise(direct[ok], k2)
        rows.append({"label": label, "pitch_mm": p, "ratio": p / p0, "kernel_size": k2, "points": int(ok.sum()),
                     "olf": psf_scores(area_resample(net[ok], p0, p, k2), ref, scale="sum"),
                     "traced": psf_scores(area_resample(traced0[ok], p0, p, k2), ref, scale="sum")})
    log(f"  {lens.id} pixel pitches: {len(rows)} pitches x {len(f)} points traced in "
        f"{time.perf_counter() - t:.1f} s")
    return rows


def pitch_markdown(lens_id: str, rows: list[dict]) -> list[str]:
    """The pitch-resampling table (Markdown lines)."""
    out = [f"{lens_id}, kernels at coarser pixel pitches ({rows[0]['points']} points: fields "
           f"{', '.join(f'{v:g}' for v in PITCH_FIELDS)} x depths {', '.join(f'{v:g}' for v in PITCH_DEPTHS_M)} m), "
           "against kernels traced at that pitch:", "",
           "| pitch | um | x learned | k | OLF resampled rel. L1 | OLF PSNR 8-bit dB | OLF PSNR sum dB "
           "| traced, resampled rel. L1 | traced, resampled PSNR 8-bit dB | PSNR sum dB |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o, t = r["olf"], r["traced"]
        tr = ("(the reference itself) | | " if t is None else
              f"{t['rel_l1']:.4f} | {t['psnr_8bit']:.2f} | {t['psnr_sum']:.2f}")
        out.append(f"| {r['label']} | {r['pitch_mm'] * 1000:.2f} | {r['ratio']:.3f} | {r['kernel_size']} | "
                   f"{o['rel_l1']:.4f} | {o['psnr_8bit']:.2f} | {o['psnr_sum']:.2f} | {tr} |")
    return out + [""]


def _psnr_image(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def timed_job(what: str, lens, geom, img, depth, library) -> tuple:
    """(image, seconds) of a simulation (``what`` 'simulate', no distortion)
    or an occlusion-aware bokeh at the prescribed focus of ``img`` with PSFs
    from ``library``."""
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.render.simulate import LensSimulator, SimulateOptions
    t = time.perf_counter()
    if what == "simulate":
        r = LensSimulator(lens, SimulateOptions(geometry=geom, distortion=False), library=library)(img, depth)
    else:
        r = bokeh(img, depth, lens, BokehOptions(focus_m="prescribed", geometry=geom), library=library)
    return r.image, time.perf_counter() - t


def downstream(olf: OmniLensField, sim_lens, bokeh_lens, height: int, width: int, log) -> dict:
    """Simulation (``sim_lens``) and bokeh (``bokeh_lens``, prescribed focus)
    of the synthetic scene, OLF PSFs against the traced library's (image
    PSNR, peak 1), at the learned pitch."""
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.synthetic import synthetic_rgbd
    img, depth = synthetic_rgbd(height, width, seed=0)
    out = {"image": [height, width]}
    for what, lens in (("simulate", sim_lens), ("bokeh", bokeh_lens)):
        if lens is None:
            continue
        entry = olf.lens_entry(lens.id)
        geom = ImageGeometry.from_pixel_pitch(lens, height, width, float(entry["pixel_pitch_mm"]))
        grid = LibraryGrid(**entry["library_grid"])
        olib = OLFLibrary(olf, lens, grid)
        traced, _ = traced_library(entry, lens)      # at the OLF's kernel size (its 99 % energy size)
        res = {}
        for name, lib in (("olf", olib), ("library", traced)):
            res[name] = timed_job(what, lens, geom, img, depth, lib)
        out[what] = {"lens": lens.id, "psnr_db": _psnr_image(res["olf"][0], res["library"][0]),
                     "olf_s": res["olf"][1], "library_s": res["library"][1],
                     "sharp_psnr_db": _psnr_image(img, res["library"][0])}
        log(f"  {what} {lens.id} {height} x {width}: OLF vs library {out[what]['psnr_db']:.2f} dB "
            f"(the blur itself: sharp vs library {out[what]['sharp_psnr_db']:.2f} dB)")
    return out


def _fmt(v, spec=".2f"):
    return "n/a" if v is None else format(v, spec)


def run_report(olf_files=None, out="out/report", *, quick: bool = False, sweep=None, pitch_only: bool = False,
               held_out_points=None, ceiling_rays=None, frame_px=(), reference_rays=(), log=print) -> int:
    """The report (module docstring) into ``out`` (olf.md, olf.json, the plot);
    ``pitch_only``: only the pixel-pitch tables (``pitch_resampling``, every
    served lens; a minute or two), into olf-pitch.md / olf-pitch.json."""
    if pitch_only:
        return _run_pitch_report(olf_files, Path(out), log)
    if held_out_points:
        return _run_comparison(olf_files, held_out_points, Path(out), log, ceiling_rays, frame_px, reference_rays)
    out = Path(out)
    files = [Path(f) for f in (olf_files or shipped_olf_files())]
    if not files:
        from dcdi_core.errors import ModelError
        raise ModelError("no OLF file given and none ships with this engine: python -m lab report olf --olf FILE.npz")
    n_points = 6 if quick else 48
    h, w = (128, 192) if quick else (1280, 1920)
    dh, dw = (96, 144) if quick else (640, 960)
    result = {"files": [], "sweep": [], "library_errors": LIBRARY_ERRORS, "paper": PAPER_POINT, "quick": quick}
    for path in files:
        olf = OmniLensField.load(path)
        info = olf.info()
        log(f"report olf: {path} ({info['variant']}, {info['hidden_layers']} x {info['width']}, "
            f"{info['bytes']} bytes)")
        lenses = {e["id"]: load_lens(e["id"]) for e in info["lenses"]}
        served = {i: l for i, l in lenses.items() if olf.covers(l)}
        rec = {"file": str(path), "bytes": info["bytes"], "parameters": info["parameters"], "dtype": info["dtype"],
               "hidden_layers": info["hidden_layers"], "width": info["width"],
               "training_s": (info["training"] or {}).get("seconds"),
               "iterations": (info["training"] or {}).get("iterations"),
               "held_out": info["held_out"], "fresh": {}, "not_served": sorted(set(lenses) - set(served))}
        for i, (lid, lens) in enumerate(served.items()):
            rec["fresh"][lid] = lens_figures(olf, lens, n_points, REPORT_SEED + i, log)
        rec["pitch"] = {lid: pitch_resampling(olf, lens, log) for lid, lens in served.items()}
        first = next(iter(served.values()), None)
        if first is not None:
            rec["map"] = map_times(olf, first, h, w, log, repeat=1 if quick else 2)
            bokeh_lens = served.get("6p") or served.get("double-gauss") or first
            rec["downstream"] = downstream(olf, first, bokeh_lens, dh, dw, log)
        result["files"].append(rec)
    if sweep:
        with open(sweep, encoding="utf-8") as f:
            result["sweep"] = [json.loads(line) for line in f if line.strip()]
    write_report(out, "olf", result, markdown(result), plot, log)
    return 0


def _run_pitch_report(olf_files, out: Path, log) -> int:
    files = [Path(f) for f in (olf_files or shipped_olf_files())]
    if not files:
        from dcdi_core.errors import ModelError
        raise ModelError("no OLF file given and none ships with this engine: python -m lab report olf --olf FILE.npz")
    result, lines = {"files": []}, []
    for path in files:
        olf = OmniLensField.load(path)
        log(f"report olf (pixel pitches): {path}")
        served = {e["id"]: load_lens(e["id"]) for e in olf.meta["lenses"]}
        rows = {lid: pitch_resampling(olf, lens, log) for lid, lens in served.items() if olf.covers(lens)}
        result["files"].append({"file": str(path), "pitch": rows})
        lines += [f"`{path}`:", ""] + [x for lid, r in rows.items() for x in pitch_markdown(lid, r)]
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "olf-pitch.json", json.dumps(result, indent=1, default=float) + "\n")
    md = "\n".join(lines) + "\n"
    write_text(out / "olf-pitch.md", md)
    log(md)
    log(f"wrote {out / 'olf-pitch.md'} and {out / 'olf-pitch.json'}")
    return 0


def held_out_comparison(olf_files, points_file, ceiling_rays=None, frame_px=(), reference_rays=()) -> list[dict]:
    """Each OLF file scored on the held-out points of a run's ``points.npz``
    (coordinates field, depth_m, focus_m: NaN at the prescribed focus, and
    the traced kernels): rows of file, lens, focus band, points and scores.
    Where a file's kernel is larger than the points', its kernels are
    cropped to theirs (renormalised), and the other way round."""
    from dcdi_core.models.olf.data import crop_normalise
    from dcdi_core.models.olf.export import FOCUS_BANDS, focus_bands
    with np.load(points_file, allow_pickle=False) as z:
        pts = {k: z[k] for k in z.files}
    rows, ceilings = [], {}
    for path in olf_files:
        olf = OmniLensField.load(path)
        for lid in olf.lens_ids:
            if f"{lid}.val.y" not in pts or not olf.covers(lens := load_lens(lid)):
                continue
            y = pts[f"{lid}.val.y"]
            fm = pts.get(f"{lid}.val.focus_m", np.full(len(y), np.nan))
            entry = olf.lens_entry(lid)
            rng_d = entry.get("focus_diopters_range") or [0.0, 1.0 / 0.7]
            bands = focus_bands(fm, rng_d)
            for band in FOCUS_BANDS:
                sel = bands == band
                if not sel.any() or (band != "prescribed" and entry.get("focus_range_m") is None):
                    continue
                focus = None if band == "prescribed" else fm[sel]
                try:
                    pred = olf.psf(lens, pts[f"{lid}.val.field"][sel], pts[f"{lid}.val.depth_m"][sel], focus,
                                   dtype=np.float64)
                except Exception as e:  # noqa: BLE001 - outside this file's range: said, not scored
                    rows.append({"file": str(path), "lens": lid, "band": band, "n": int(sel.sum()),
                                 "not_served": str(e)})
                    continue
                ref = y[sel]
                k = min(pred.shape[-1], ref.shape[-1])
                pred, ref = crop_normalise(pred, k), crop_normalise(ref, k)
                rows.append({"file": str(path), "lens": lid, "band": band, "k": k, "n": int(sel.sum()),
                             **psf_scores(pred, ref, scale="sum")})
                if lid not in ceilings:
                    ceilings[lid] = (lens, entry)
    return rows + raymap_rows(pts, ceilings, ceiling_rays) + frame_rows(pts, ceilings, frame_px or ()) \
        + reference_rows(pts, ceilings, reference_rays, ceiling_rays)


# a blur-scaled frame: the kernel's pixels spaced max(1, (FRAME_MARGIN x blur + FRAME_PAD_PX) / M) pixels apart
FRAME_MARGIN, FRAME_PAD_PX = 1.15, 4.0


def frame_round_trip(kernels, blur_px, frame_px: int) -> np.ndarray:
    """Kernels (n, 3, k, k) summing to 1 per channel, through an M = ``frame_px``
    frame scaled to each one's thin-lens blur (``blur_px``, diameter): area-
    resampled into it where the blur is wider than the frame, then back to
    the pixel grid by linear interpolation and renormalised. What a network
    whose head draws M x M kernels in blur-scaled coordinates can hold at
    best (its representation's own error)."""
    from dcdi_core.psf.pitch import area_resample
    y = np.asarray(kernels, np.float64)
    k, m, out = y.shape[-1], int(frame_px), np.zeros_like(y)
    for i, b in enumerate(np.asarray(blur_px, np.float64)):
        step = max(1.0, (FRAME_MARGIN * b + FRAME_PAD_PX) / m)
        if step > 1.0:
            frame = area_resample(y[i], 1.0, step, m)
        else:
            h = min(m, k) // 2
            frame = np.zeros((3, m, m))
            frame[:, m // 2 - h:m // 2 + h + 1, m // 2 - h:m // 2 + h + 1] = y[i, :, k // 2 - h:k // 2 + h + 1,
                                                                                k // 2 - h:k // 2 + h + 1]
        u = _linear_matrix(k, m, step)
        back = np.einsum("im,cmn,jn->cij", u, frame, u)
        out[i] = back / np.maximum(back.sum(axis=(-1, -2), keepdims=True), 1e-300)
    return out


def _linear_matrix(k: int, m: int, step: float) -> np.ndarray:
    """(k, m): linear interpolation from m frame samples ``step`` pixels apart to k pixel centres (both centred)."""
    xo = np.arange(k) - k // 2
    xf = (np.arange(m) - m // 2) * step
    j = np.clip(np.searchsorted(xf, xo) - 1, 0, m - 2)
    t = (xo - xf[j]) / (xf[j + 1] - xf[j])
    inside = (xo >= xf[0]) & (xo <= xf[-1])
    u = np.zeros((k, m))
    u[np.arange(k)[inside], j[inside]] = 1.0 - t[inside]
    u[np.arange(k)[inside], j[inside] + 1] += t[inside]
    return u


def frame_rows(pts: dict, lenses: dict, sizes) -> list[dict]:
    """The held-out PSFs of each lens through blur-scaled frames of ``sizes``
    px (:func:`frame_round_trip`), scored against themselves: the ceiling of
    a head that draws a disc of any radius in a fixed number of outputs."""
    from dcdi_core.optics.paraxial import prescribed_focus_diopters
    from dcdi_core.psf.sampling import blur_px_per_diopter
    rows = []
    for lid, (lens, entry) in lenses.items():
        y = pts[f"{lid}.val.y"]
        d = pts[f"{lid}.val.depth_m"]
        fm = pts.get(f"{lid}.val.focus_m", np.full(len(y), np.nan))
        focus_d = np.where(np.isnan(fm), prescribed_focus_diopters(lens), 1.0 / np.where(np.isnan(fm), 1.0, fm))
        with np.errstate(divide="ignore"):
            blur = blur_px_per_diopter(lens, float(entry["pixel_pitch_mm"])) * np.abs(1.0 / d - focus_d)
        for m in sizes:
            rows.append({"file": f"the held-out PSFs through a {m} px blur-scaled frame", "lens": lid,
                         "band": "all", "k": int(y.shape[-1]), "n": len(y),
                         **psf_scores(frame_round_trip(y, blur, m), y, scale="sum")})
    return rows


def raymap_rows(pts: dict, lenses: dict, rays=None, refs: dict | None = None, against: str = "") -> list[dict]:
    """The ceiling of an OLF learned from a ray map: the lens's shipped ray
    map itself on the same held-out points, deposited with the settings the
    OLF learned (its rays, wavelengths, pitch and kernel), per focus band
    (``lenses``: {id: (lens, the OLF's entry)}; a lens without a ray map is
    left out); ``rays``: rows with these rays a side instead (None: the OLF's);
    ``refs``: {id: kernels} scored against instead of the stored traces
    (``against`` says which, in the rows' file column)."""
    from dataclasses import replace

    from dcdi_core.models.olf.data import crop_normalise, raymap_points
    from dcdi_core.models.olf.export import FOCUS_BANDS, focus_bands
    from dcdi_core.psf.raymap import open_raymap
    from dcdi_core.shipped import raymap_file
    rows = []
    for lid, (lens, entry) in lenses.items():
        path = raymap_file(lid)
        if path is None:
            continue
        y = pts[f"{lid}.val.y"] if refs is None else refs[lid]
        fm = pts.get(f"{lid}.val.focus_m", np.full(len(y), np.nan))
        learned = replace(_settings(entry), pixel_pitch_mm=float(entry["pixel_pitch_mm"]),
                          kernel_size=int(y.shape[-1]))
        bands = focus_bands(fm, entry.get("focus_diopters_range") or [0.0, 1.0 / 0.7])
        for n_rays in rays or [learned.pupil_samples]:
            psf, ok = raymap_points(open_raymap(path), lens, replace(learned, pupil_samples=int(n_rays)),
                                    pts[f"{lid}.val.field"], pts[f"{lid}.val.depth_m"], fm)
            for band in ("all",) + tuple(FOCUS_BANDS):
                sel = ok & (True if band == "all" else bands == band)
                if sel.any():
                    rows.append({"file": f"ray map, {n_rays} rays a side{against}", "lens": lid, "band": band,
                                 "k": int(y.shape[-1]), "n": int(sel.sum()),
                                 **psf_scores(crop_normalise(psf[sel], y.shape[-1]), y[sel], scale="sum")})
    return rows


def reference_rows(pts: dict, lenses: dict, rays, ceiling_rays=None) -> list[dict]:
    """The held-out references' own error: each point traced again with
    ``rays`` a side (more than the stored traces), the stored traces scored
    against them, and the ray map (``ceiling_rays``) against them too. A
    store that reaches the stored traces' own error cannot be told from them."""
    from dataclasses import replace

    from dcdi_core.models.olf.data import crop_normalise, trace_points
    rows = []
    for n_rays in rays or ():
        refs = {}
        for lid, (lens, entry) in lenses.items():
            y = pts[f"{lid}.val.y"]
            fm = pts.get(f"{lid}.val.focus_m", np.full(len(y), np.nan))
            s = replace(_settings(entry), pixel_pitch_mm=float(entry["pixel_pitch_mm"]), kernel_size=int(y.shape[-1]),
                        pupil_samples=int(n_rays))
            again, ok = trace_points(lens, s, pts[f"{lid}.val.field"], pts[f"{lid}.val.depth_m"], fm)
            refs[lid] = np.where(ok[:, None, None, None], crop_normalise(again, y.shape[-1]), y)
            rows.append({"file": f"the held-out traces against {n_rays}-ray traces", "lens": lid, "band": "all",
                         "k": int(y.shape[-1]), "n": int(ok.sum()), **psf_scores(y[ok], refs[lid][ok], scale="sum")})
        rows += raymap_rows(pts, lenses, ceiling_rays, refs, f", against {n_rays}-ray traces")
    return rows


def comparison_markdown(rows: list[dict], points_file) -> str:
    lines = [f"Held-out points of `{points_file}` (traced, never trained on), per file, lens and focus band:", "",
             "| file | lens | focus | points | k | PSNR 8-bit dB: mean | median | worst | SSIM | rel. L1 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "not_served" in r:
            lines.append(f"| {r['file']} | {r['lens']} | {r['band']} | {r['n']} | not served: {r['not_served']} "
                         "| | | | | |")
        else:
            lines.append(f"| {r['file']} | {r['lens']} | {r['band']} | {r['n']} | {r['k']} | {r['psnr_8bit']:.2f} | "
                         f"{r['psnr_8bit_median']:.2f} | {r['psnr_8bit_worst']:.2f} | "
                         f"{_fmt(r['ssim_8bit'], '.4f')} | {r['rel_l1']:.4f} |")
    return "\n".join(lines) + "\n"


def _run_comparison(olf_files, points_file, out: Path, log, ceiling_rays=None, frame_px=(), reference_rays=()) -> int:
    files = [Path(f) for f in (olf_files or shipped_olf_files())]
    rows = held_out_comparison(files, points_file, ceiling_rays, frame_px, reference_rays)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "olf-held-out.json", json.dumps(rows, indent=1, default=float) + "\n")
    md = comparison_markdown(rows, points_file)
    write_text(out / "olf-held-out.md", md)
    log(md)
    log(f"wrote {out / 'olf-held-out.md'} and {out / 'olf-held-out.json'}")
    return 0


def markdown(result: dict) -> str:
    lines = []
    if result["sweep"]:
        lines += ["Sweep (one lens, 1 thread, equal wall time per size; held-out, EMA weights):", "",
                  "| variant | size (N x W) | lr | iterations | train min | parameters | float16 file "
                  "| 4 lenses, float16 | PSNR 8-bit dB | PSNR sum dB | SSIM | rel. L1 | float16 changes PSNR by |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        from dcdi_core.models.olf.spec import SIZES
        for r in result["sweep"]:
            t, f16 = r["torch"], r["float16"]
            n, wd = SIZES[r["size"]]
            lines.append(f"| {r.get('variant', 'radial')} | {r['size']} ({n} x {wd}) | {r['lr']:g} | {r['iters']} | {r['seconds'] / 60:.1f} | "
                         f"{r['params']:,} | {f16['bytes'] / 1e6:.2f} MB | {r['four_lens_params'] * 2 / 1e6:.1f} MB | "
                         f"{t['psnr_8bit']:.2f} | {t['psnr_sum']:.2f} | {_fmt(t['ssim_8bit'], '.4f')} | "
                         f"{t['rel_l1']:.4f} | {f16['held_out']['psnr_8bit'] - t['psnr_8bit']:+.3f} dB |")
        lines.append("")
    le = result["library_errors"]
    for rec in result["files"]:
        train_min = "n/a" if rec["training_s"] is None else f"{rec['training_s'] / 60:.1f}"
        lines += [f"`{rec['file']}`: {rec['hidden_layers']} x {rec['width']}, {rec['parameters']:,} parameters, "
                  f"{rec['bytes'] / 1e6:.2f} MB ({rec['dtype']}), {rec['iterations']} iterations in {train_min} "
                  "min of 1-thread training" + (f"; not served (changed prescription): {', '.join(rec['not_served'])}"
                                                 if rec["not_served"] else ""), "",
                  "| lens | held-out PSNR 8-bit dB | PSNR sum dB | SSIM | rel. L1 | fresh points: OLF rel. L1 "
                  "| library (interpolated) rel. L1 | OLF PSNR 8-bit | library PSNR 8-bit |",
                  "|---|---|---|---|---|---|---|---|---|"]
        per = (rec["held_out"] or {}).get("lenses", {})
        for lid, fr in rec["fresh"].items():
            hh = per.get(lid, {})
            lines.append(f"| {lid} | {_fmt(hh.get('psnr_8bit'))} | {_fmt(hh.get('psnr_sum'))} | "
                         f"{_fmt(hh.get('ssim_8bit'), '.4f')} | {_fmt(hh.get('rel_l1'), '.4f')} | "
                         f"{fr['olf']['rel_l1']:.4f} | {fr['library']['rel_l1']:.4f} | "
                         f"{fr['olf']['psnr_8bit']:.2f} | {fr['library']['psnr_8bit']:.2f} |")
        mean = (rec["held_out"] or {}).get("mean")
        if mean:
            lines.append(f"| mean | {mean['psnr_8bit']:.2f} | {mean['psnr_sum']:.2f} | {_fmt(mean['ssim_8bit'], '.4f')} "
                         f"| {mean['rel_l1']:.4f} | | | | |")
        focus = (rec["held_out"] or {}).get("focus") or {}
        if focus:
            lines += ["", "Held-out per focus (the learned diopter range in thirds; prescribed: the lens as "
                          "prescribed):", "", "| lens | focus | points | PSNR 8-bit dB | SSIM | rel. L1 |",
                      "|---|---|---|---|---|---|"]
            for lid, bands in focus.items():
                for band, hb in sorted(bands.items(), key=lambda b: ("prescribed", "far", "mid", "near").index(b[0])):
                    lines.append(f"| {lid} | {band} | {hb['n']} | {hb['psnr_8bit']:.2f} | "
                                 f"{_fmt(hb['ssim_8bit'], '.4f')} | {hb['rel_l1']:.4f} |")
        lines += ["", f"The library's own errors (`python -m lab report psf-accuracy mos-s1`): interpolation "
                      f"between depth bins {le['interpolation_depth']}, between fields {le['interpolation_field']}, ray sampling "
                      f"{le['sampling']} (relative L1).", ""]
        for lid, rows in rec.get("pitch", {}).items():
            lines += pitch_markdown(lid, rows)
        if "map" in rec:
            m = rec["map"]
            lines += [f"PSF map of {m['image'][0]} x {m['image'][1]} ({m['patches']} patches): traced library in "
                      f"memory {m['library']:.3f} s; OLF-backed library {m['olf']:.3f} s, of which the network "
                      f"{m['network'] * 1e3:.1f} ms ({m['bins']} depth bins x the grid's fields); the network once per "
                      f"patch {m['network_per_patch'] * 1e3:.1f} ms.", ""]
        if "downstream" in rec:
            d = rec["downstream"]
            for what in ("simulate", "bokeh"):
                if what in d:
                    x = d[what]
                    lines.append(f"{what} ({x['lens']}, synthetic scene {d['image'][0]} x {d['image'][1]}): OLF PSFs "
                                 f"vs traced library PSFs {x['psnr_db']:.2f} dB image PSNR (the blur itself, sharp vs "
                                 f"library: {x['sharp_psnr_db']:.2f} dB); {x['olf_s']:.2f} s vs {x['library_s']:.2f} s")
            lines.append("")
    return "\n".join(lines) + "\n"


def plot(result: dict, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r in result["sweep"]:
        for dt, marker in (("float32", "o"), ("float16", "s")):
            ax.scatter(r[dt]["bytes"] / 1e6, r[dt]["held_out"]["psnr_8bit"], marker=marker, s=22,
                       color="C0" if r["lr"] >= 1e-3 else "C1")
        ax.annotate(f"{r['size']} {r['lr']:g}", (r["float16"]["bytes"] / 1e6, r["float16"]["held_out"]["psnr_8bit"]),
                    fontsize=7, xytext=(3, 3), textcoords="offset points")
    for rec in result["files"]:
        mean = (rec["held_out"] or {}).get("mean")
        if mean:
            ax.scatter(rec["bytes"] / 1e6, mean["psnr_8bit"], marker="*", s=120, color="C3")
            ax.annotate(os.path.basename(rec["file"]), (rec["bytes"] / 1e6, mean["psnr_8bit"]), fontsize=7,
                        xytext=(4, -10), textcoords="offset points")
    p = result["paper"]
    ax.scatter(p["megabytes"], p["psnr_8bit"], marker="D", s=50, color="k")
    ax.annotate(p["label"], (p["megabytes"], p["psnr_8bit"]), fontsize=7, xytext=(-105, 6), textcoords="offset points")
    ax.axvline(24, color="grey", lw=0.8, ls="--")
    ax.text(24, ax.get_ylim()[0], " 24 MB", fontsize=7, color="grey", va="bottom")
    ax.set_xscale("log")
    ax.set_xlabel("storage (MB)")
    ax.set_ylabel("held-out PSF PSNR, 8-bit peak scale (dB)")
    ax.set_title("Omni-Lens-Field: error against storage\n(sweep, one lens: circles float32, squares float16; "
                 "blue lr 1e-3, orange 3e-4; stars: OLF files)", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    save_figure(fig, path)
