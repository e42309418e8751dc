"""The catalogue's ray maps against tracing, at held-out field, depth, focus,
f-number and blades, and beside a per-lens PSF basis on storage against
accuracy.

For each catalogue lens with a shipped ray map (``dcdi_core/psf/data/
raymap``), ``--points`` points drawn with a seed (and the lens's id): field uniform in [0, 1];
depth uniform in diopters from 0.7 m to infinity, one in eight at infinity;
half refocused (focus uniform in diopters from 0.8 m to infinity); half
stopped down to 1.4-8 x the wide-open f-number, with 0, 5, 6, 7 or 9 blades
at a random turn. Each point's pixel pitch starts at the catalogue sensor's
6 um and grows until a 129 px kernel holds 99 % of the rays (a quick trace).
The reference is the trace with ``--rays`` per pupil side (512 by default,
31 wavelengths). Every kernel of this report is deposited with the paper's
Gaussian (sigma = sqrt(2)/3 px): with the ray histogram (sigma 0), traces of
one wide blur with 512 and 1024 rays differ by 24-27 dB (the ray grid's
moire against the pixels), which would hide the map's own error. Figures, PSNR on the paper's scale (each channel over its
peak, 8-bit), mean and (worst) over the points:

- the ray map with the same rays: what the map's polynomials and their
  interpolation cost (the map launches the very rays the tracer does);
- the ray map and the trace with the serving default, 64 rays per side,
  each against the reference: what a user gets from either;
- seconds of one PSF at 64 rays (wall, one thread), map and trace.

``--basis-lens``: that lens's library traced at its prescribed focus, wide
open, at 37.5 um (a 960 x 640 frame of a 36 x 24 mm sensor), 32 fields x 20
depth bins + infinity over 0.7 m to infinity, 128 rays, compressed by SVD at
several ranks (``psf.basis``), against its ray map at held-out fields and
depths of that one focus, stop and pitch: the storage each needs for the
accuracy.

Run ``python -m lab raymap`` (about 15 minutes on 2 cores; docs/psf.md).
"""
from __future__ import annotations

import math
import time
import warnings

import numpy as np

REFERENCE_RAYS = 512
SIGMA_PX = math.sqrt(2.0) / 3.0     # the paper's deposit (psf.deposit): no moire between ray grid and pixels
SERVING_RAYS = 64
START_PITCH_MM = 0.006
KERNEL = 129
BASIS_PITCH_MM = 0.0375
BASIS_RANKS = (16, 48, 96)


def _psnr(pred: np.ndarray, ref: np.ndarray) -> float:
    from lab.psf_source_report import point_scores
    return float(point_scores(pred[None], ref[None])["psnr_8bit"][0])


def draw_points(lens, n: int, seed: int) -> list[dict]:
    """The held-out points of one lens (see the module's docstring)."""
    from dcdi_core.optics.aperture import wide_open_f_number
    rng = np.random.default_rng(seed)
    n0 = wide_open_f_number(lens)
    out = []
    for i in range(n):
        g = rng.uniform(0.0, 1.0 / 0.7)
        depth = math.inf if i % 8 == 7 else 1.0 / max(g, 1e-6)
        focus = 1.0 / rng.uniform(1e-3, 1.0 / 0.8) if i % 2 == 1 else None
        stopped = i % 4 in (2, 3)
        out.append({"field": float(rng.uniform(0.0, 1.0)), "depth_m": float(depth),
                    "focus_m": None if focus is None else float(focus),
                    "f_number": float(n0 * 2 ** rng.uniform(0.5, 3.0)) if stopped else None,
                    "blades": int(rng.choice([0, 5, 6, 7, 9])) if stopped else 0,
                    "rotation_deg": float(rng.uniform(0.0, 60.0))})
    return out


def _lens_at(lens, point):
    from dcdi_core.optics.aperture import Aperture, stopped_down
    if point["f_number"] is None and not point["blades"]:
        return lens
    return stopped_down(lens, Aperture(f_number=point["f_number"], blades=point["blades"],
                                       rotation_deg=point["rotation_deg"] if point["blades"] else 0.0))


def _pitch_for(lens, point) -> float:
    """The finest pitch from 6 um up at which a 129 px kernel holds the point's blur."""
    from dcdi_core.psf.compute import PSFSettings, psf
    pitch = START_PITCH_MM
    for _ in range(8):
        s = PSFSettings(kernel_size=KERNEL, pupil_samples=48, n_wavelengths=7, pixel_pitch_mm=pitch,
                        focus_distance_m=point["focus_m"])
        r = psf(lens, depth_m=point["depth_m"], field=point["field"], settings=s)
        need = int(r.kernel_size_needed)
        if need <= KERNEL - 8 and float(r.energy_outside.max()) <= 0.01:
            return pitch
        pitch *= max(1.25, (need or 2 * KERNEL) / (KERNEL - 16))
    return pitch


def _map_kernel(rm, lens, point, settings):
    from dcdi_core.psf.library import LibraryGrid
    from dcdi_core.psf.raymap import RayMapLibrary
    lib = RayMapLibrary(rm, lens, settings, LibraryGrid(n_fields=2, n_depths=2, near_m=max(0.7, rm.near_m)))
    return lib.kernels(point["field"], point["depth_m"])


def lens_rows(lens_id: str, n_points: int, seed: int, rays: int, log=print) -> dict:
    """The figures of one lens (its points and their means)."""
    from dataclasses import replace

    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
    from dcdi_core.psf.raymap import open_raymap
    from dcdi_core.shipped import raymap_file
    base = load_lens(lens_id)
    path = raymap_file(lens_id)
    rm = open_raymap(path)
    pts = []
    import zlib
    for point in draw_points(base, n_points, seed + zlib.crc32(lens_id.encode()) % 10007):
        lens = _lens_at(base, point)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            pitch = _pitch_for(lens, point)
            s = PSFSettings(kernel_size=KERNEL, pupil_samples=rays, pixel_pitch_mm=pitch,
                            focus_distance_m=point["focus_m"], deposit_sigma_px=SIGMA_PX)
            ref = psf(lens, depth_m=point["depth_m"], field=point["field"], settings=s).psf
            same = _map_kernel(rm, lens, point, s)
            s64 = replace(s, pupil_samples=SERVING_RAYS)
            t = time.perf_counter()
            m64 = _map_kernel(rm, lens, point, s64)
            t_map = time.perf_counter() - t
            t = time.perf_counter()
            tr64 = psf(lens, depth_m=point["depth_m"], field=point["field"], settings=s64).psf
            t_trace = time.perf_counter() - t
        row = dict(point, pitch_mm=pitch, same_rays=_psnr(same, ref), map64=_psnr(m64, ref),
                   trace64=_psnr(tr64, ref), t_map=t_map, t_trace=t_trace)
        pts.append(row)
        log(f"  {lens_id}: field {point['field']:.2f} depth {point['depth_m']:.3g} m focus {point['focus_m']} "
            f"f/{point['f_number'] or 0:.3g} {point['blades']} blades at {pitch * 1000:.3g} um: same rays "
            f"{row['same_rays']:.2f} dB, 64 rays map {row['map64']:.2f} / trace {row['trace64']:.2f} dB")

    def agg(key):
        v = np.array([p[key] for p in pts])
        return float(v.mean()), float(v.min())
    return {"lens": lens_id, "mb": path.stat().st_size / 1e6, "points": pts, "same_rays": agg("same_rays"),
            "map64": agg("map64"), "trace64": agg("trace64"),
            "t_map": float(np.median([p["t_map"] for p in pts])),
            "t_trace": float(np.median([p["t_trace"] for p in pts]))}


def format_lens_table(rows: list[dict], rays: int) -> str:
    out = [f"| lens | ray map MB | map vs trace, {rays} rays: mean (worst) dB | 64 rays vs the {rays}-ray trace: "
           "map / trace, mean (worst) dB | one PSF at 64 rays: map / trace s |",
           "|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| `{r['lens']}` | {r['mb']:.2f} | {r['same_rays'][0]:.2f} ({r['same_rays'][1]:.2f}) | "
                   f"{r['map64'][0]:.2f} ({r['map64'][1]:.2f}) / {r['trace64'][0]:.2f} ({r['trace64'][1]:.2f}) | "
                   f"{r['t_map']:.2f} / {r['t_trace']:.2f} |")
    allp = [p for r in rows for p in r["points"]]
    same = np.array([p["same_rays"] for p in allp])
    out.append(f"| all {len(rows)} lenses, {len(allp)} points | {sum(r['mb'] for r in rows):.2f} | "
               f"{same.mean():.2f} ({same.min():.2f}) | "
               f"{np.mean([p['map64'] for p in allp]):.2f} ({min(p['map64'] for p in allp):.2f}) / "
               f"{np.mean([p['trace64'] for p in allp]):.2f} ({min(p['trace64'] for p in allp):.2f}) | |")
    return "\n".join(out)


def basis_rows(lens_id: str, n_points: int, seed: int, rays: int, log=print) -> list[dict]:
    """The PSF basis of ``lens_id`` at several ranks beside its ray map, at one focus, stop and pitch."""
    from dataclasses import replace

    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.basis import BasisLibrary, compress
    from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
    from dcdi_core.psf.library import LibraryGrid, PSFLibrary
    from dcdi_core.psf.raymap import open_raymap
    from dcdi_core.shipped import raymap_file as shipped_raymap
    lens = load_lens(lens_id)
    rm = open_raymap(shipped_raymap(lens_id))
    grid = LibraryGrid(n_fields=32, n_depths=20, near_m=0.7, far_m=10.0)
    rng = np.random.default_rng(seed + 1)
    points = [(float(rng.uniform(0, 1)), 1.0 / float(rng.uniform(0.1, 1 / 0.7))) for _ in range(n_points)]
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        probe = psf(lens, depth_m=0.7, field=0.0, settings=PSFSettings(kernel_size=KERNEL, pupil_samples=48,
                                                                       n_wavelengths=7,
                                                                       pixel_pitch_mm=BASIS_PITCH_MM))
        k = min(KERNEL, max(41, int(probe.kernel_size_needed) or 0) | 1)
        s = PSFSettings(kernel_size=k, pupil_samples=128, pixel_pitch_mm=BASIS_PITCH_MM, deposit_sigma_px=SIGMA_PX)
        t = time.perf_counter()
        library = PSFLibrary(lens, s, grid, None)
        library.build()
        trace_s = time.perf_counter() - t
        log(f"  {lens_id}: library of {grid.n_fields} x {grid.n_depths + 1} traced in {trace_s:.0f} s, {k} px")
        refs = [psf(lens, depth_m=d, field=f, settings=replace(s, pupil_samples=rays)).psf
                for f, d in points]
        for rank in BASIS_RANKS:
            store = compress(library, rank)
            mb = sum(a.nbytes for a in store.file_arrays().values()) / 1e6     # as its file holds them
            blib = BasisLibrary(store, lens)
            got = [blib.kernels(f, d) for f, d in points]
            v = np.array([_psnr(g, r) for g, r in zip(got, refs)])
            rows.append({"store": f"PSF basis, rank {rank}", "covers": "this focus, f-number and pitch (and "
                         "coarser pitches)", "mb": mb, "mean": float(v.mean()), "worst": float(v.min())})
        for r_ in (SERVING_RAYS, 256):
            s2 = replace(s, pupil_samples=r_)
            v = np.array([_psnr(_map_kernel(rm, lens, {"field": f, "depth_m": d}, s2), ref)
                          for (f, d), ref in zip(points, refs)])
            rows.append({"store": f"ray map, {r_} rays", "covers": "any focus, f-number, blades, pitch",
                         "mb": shipped_raymap(lens_id).stat().st_size / 1e6, "mean": float(v.mean()),
                         "worst": float(v.min())})
    return rows


def format_basis_table(rows: list[dict]) -> str:
    out = ["| store | serves | MB | mean (worst) dB |", "|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['store']} | {r['covers']} | {r['mb']:.2f} | {r['mean']:.2f} ({r['worst']:.2f}) |")
    return "\n".join(out)


def main(argv=None) -> int:
    import argparse
    import json
    from pathlib import Path

    from dcdi_core.shipped import RAYMAP_DIR
    p = argparse.ArgumentParser(prog="python -m lab raymap",
                                description="the catalogue's ray maps against tracing (module docstring)")
    p.add_argument("--lens", action="append", default=None, help="lens id (repeat; default: every shipped map)")
    p.add_argument("--points", type=int, default=8, help="held-out points per lens (default 8)")
    p.add_argument("--rays", type=int, default=REFERENCE_RAYS, help="the reference's rays per pupil side")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--basis-lens", default="zeiss-planar-50mm-f1-4",
                   help="the lens compared with its PSF basis ('none': skip)")
    p.add_argument("--json", default=None, help="write every figure here")
    args = p.parse_args(argv)
    lenses = args.lens or sorted(q.stem for q in RAYMAP_DIR.glob("*.npz"))
    rows = [lens_rows(lid, args.points, args.seed, args.rays) for lid in lenses]
    print(format_lens_table(rows, args.rays))
    total = sum(q.stat().st_size for q in RAYMAP_DIR.glob("*.npz")) / 1e6
    print(f"\nevery shipped ray map: {total:.2f} MB")
    brows = []
    if args.basis_lens != "none":
        brows = basis_rows(args.basis_lens, args.points, args.seed, args.rays)
        print()
        print(format_basis_table(brows))
    if args.json:
        Path(args.json).write_text(json.dumps({"lenses": rows, "basis": brows}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
