"""`dcdi olf train|points|info`: the Omni-Lens-Field, a network of lenses'
PSFs (trained with torch, served without it).

There is no `olf export`: `olf train` exports as it ends (the export takes the
trained network in memory, not a run folder), and the same command again
resumes a killed run and exports it.

Engine imports are inside the handlers: torch is loaded only by `olf train`.
"""
from __future__ import annotations

import math
import sys
import time

from .common import (PIXEL_PITCH_RULE, UNITS, add_device_option, add_subcommands, dump, positive_int, ran_on, run_training,
                     torchrun_worker)


def _data_config(args, **extra):
    from ..models.olf.data import PSFDataConfig
    return PSFDataConfig(lenses=tuple(args.lens), pupil_samples=args.rays, n_wavelengths=args.wavelengths,
                         n_fields=args.fields, n_depths=args.depths, focus_lenses=tuple(args.focus_lens or ()),
                         focus_range_m=tuple(args.focus_range), focus_bins=args.focus_bins, offgrid=args.offgrid,
                         held_out=args.held_out, seed=args.seed, source=args.psf_data,
                         held_out_rays=args.held_out_rays, pixel_pitch_mm=args.pixel_pitch,
                         deposit_sigma_px=args.deposit_sigma, **extra)


def cmd_olf_train(args) -> int:
    import os
    from pathlib import Path

    from ..models.olf.config import OLFTrainConfig
    data = _data_config(args, variant=args.variant)
    config = OLFTrainConfig(data=data, size=args.size, iters=args.iters, batch=args.batch, lr=args.lr,
                            seed=args.seed, threads=args.threads or (os.cpu_count() or 1),
                            checkpoint_every=args.checkpoint_every, validate_every=args.validate_every)
    from ..models.olf.export import export_olf               # torch from here on
    from ..models.olf.train import train
    run = Path(args.run or (str(args.output) + ".run"))
    result = run_training("olf train", run, lambda **kw: train(config, run, device=args.device, **kw),
                          config.checkpoint_every)
    if result is None:
        return 130
    if torchrun_worker():
        return 0                                        # rank 0 exports and reports
    meta = export_olf(result, args.output, weights=args.weights, dtype=args.dtype)
    from ..outputs import size_of
    h = meta["held_out"]["mean"]
    rate = result.step / result.seconds if result.seconds > 0 else float("nan")
    print(f"wrote {args.output} ({meta['parameters']} parameters, {size_of(args.output)} bytes; "
          f"run folder {run})")
    print(f"held-out ({args.weights}): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM "
          + (f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a")
          + f", relative L1 {h['rel_l1']:.4f}; {result.seconds:.1f} s of training ({rate:.1f} it/s; PSF data not included)")
    print(ran_on(result.where))
    return 0


def cmd_olf_points(args) -> int:
    from ..models.olf.data import build_data
    t0 = time.perf_counter()
    d = build_data(_data_config(args), points_file=args.output, log=lambda t: print(t, file=sys.stderr))
    print(f"wrote {args.output}: " + ", ".join(f"{ls.lens.id} {len(ls.val_x)} held-out" for ls in d.lenses)
          + f" ({time.perf_counter() - t0:.0f} s)")
    return 0


def cmd_olf_info(args) -> int:
    from ..psf.sources import WEIGHTS_DIR, shipped_olf_files
    from ..psf.olf import load_olf_file
    from ..psf.rayfield import RayFieldOLF
    from ..shipped import olf_rays_file
    files = args.file or [p for p in [olf_rays_file()] if p is not None] + shipped_olf_files()
    if not files:
        print(f"no OLF file ships with this engine ({WEIGHTS_DIR} holds none); give one: dcdi olf info FILE.npz")
        return 0
    infos = []
    for path in files:
        olf = load_olf_file(path)
        info = olf.info()
        info["shipped"] = not args.file
        for entry in info["lenses"]:
            entry["prescription"] = _prescription(olf, entry["id"])
        infos.append(info)
    if args.json:
        print(dump(infos[0] if args.file and len(infos) == 1 else infos))
        return 0
    for info in infos:
        (_print_rays_info if info["variant"] == "rays" else _print_olf_info)(info)
    return 0


def _prescription(olf, lens_id: str) -> str:
    """Whether the lens file of ``lens_id`` is the prescription the OLF learned."""
    from ..optics.lens import load_lens
    from ..psf.rayfield import RayFieldOLF
    try:
        lens = load_lens(lens_id)
        if isinstance(olf, RayFieldOLF):
            olf.map_for(lens_id).check_lens(lens)
            return "current"
        return "current" if olf.covers(lens) else "differs (not served)"
    except Exception as e:  # noqa: BLE001 - a lens that no longer loads or differs is reported, not fatal
        return "differs (not served)" if "fingerprint" in str(e) else f"not loadable ({e})"


def _print_rays_info(info) -> None:
    print(f"{info['file']}{' (shipped)' if info.get('shipped') else ''}: Omni-Lens-Field in ray space "
          f"(Legendre polynomials of field and 1/depth), {len(info['lenses'])} lenses, {info['bytes']} bytes")
    for e in info["lenses"]:
        h = e.get("held_out") or {}
        fig = (f"; held-out ({h['points']} points, refocused and stopped down, against {h['rays']}-ray traces) "
               f"PSNR {h['psnr_8bit'][0]:.2f} dB mean, {h['psnr_8bit'][1]:.2f} worst (its map "
               f"{h['map_psnr_8bit'][0]:.2f}, {h['map_psnr_8bit'][1]:.2f})" if h else "")
        print(f"  {e['id']:<14} degrees {e['degrees'][0]} x {e['degrees'][1]}, {e['n_wavelengths']} wavelengths, "
              f"depth from {e['near_m']} m; prescription {e['prescription']}{fig}")
    t = info.get("training") or {}
    if t.get("command"):
        print(f"  made by: {t['command']}; checksum {info['checksum'][:16]}...")


def _figures(h) -> str:
    return (f"{h['psnr_8bit']:.2f} dB, SSIM " + (f"{h['ssim_8bit']:.4f}" if h.get("ssim_8bit") is not None else "n/a")
            + f", rel. L1 {h['rel_l1']:.4f}")


def _print_olf_info(info) -> None:
    print(f"{info['file']}{' (shipped)' if info.get('shipped') else ''}: {info['variant']} Omni-Lens-Field, "
          f"{info['hidden_layers']} hidden layers x {info['width']}, {info['parameters']} parameters "
          f"({info['dtype']}, {info['weights']} weights), {info['bytes']} bytes")
    per = ((info["held_out"] or {}).get("lenses")) or {}
    for e in info["lenses"]:
        focus = f", focus {e['focus_range_m']} m" if e["focus_range_m"] else ""
        h = per.get(e["id"])
        fig = f"; held-out {_figures(h)}" if h else ""
        print(f"  {e['id']:<14} k = {e['kernel_size']}, pitch {e['pixel_pitch_mm'] * 1000:.3g} um, "
              f"depth {e['depth_range_m'][0]}-{e['depth_range_m'][1]} m{focus}; prescription "
              f"{e['prescription']}{fig}")
        bands = (((info["held_out"] or {}).get("focus") or {}).get(e["id"]) or {})
        for band, hb in sorted(bands.items(), key=lambda b: ("prescribed", "far", "mid", "near").index(b[0])):
            print(f"  {'':<14}   held-out at {band} focus ({hb['n']} points): {_figures(hb)}")
    h = (info["held_out"] or {}).get("mean")
    if h:
        ssim = f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a"
        print(f"  held-out (mean over lenses): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM {ssim}, "
              f"relative L1 {h['rel_l1']:.4f}, PSNR {h['psnr_sum']:.2f} dB (sum-normalised)")
    t = info["training"] or {}
    if t:
        print(f"  trained {t.get('iterations')} iterations in {t.get('seconds', 0):.0f} s; checksum "
              f"{info['checksum'][:16]}...")


def _add_data_options(t) -> None:
    """The options of `olf train` and `olf points` that decide the traced samples."""
    t.add_argument("--offgrid", type=int, default=256, help="traced off-grid training points per lens")
    t.add_argument("--held-out", type=positive_int, default=64, help="traced held-out points per lens")
    t.add_argument("--held-out-rays", type=positive_int, default=None, metavar="N",
                   help="pupil samples per side of the traced held-out points (default: --rays); 512 scores "
                        "against converged PSFs")
    t.add_argument("--psf-data", choices=["trace", "raymap"], default="trace",
                   help="where the training PSFs come from: traced (default), or deposited from each lens's "
                        "shipped ray map (the catalogue's lenses: any focus, no tracing; a lens without one is "
                        "traced); held-out points are traced either way")
    t.add_argument("--pixel-pitch", type=float, default=None, metavar="MM", help=PIXEL_PITCH_RULE)
    t.add_argument("--deposit-sigma", type=float, default=0.0, metavar="PX",
                   help="each ray's Gaussian spread in the learned and held-out PSFs, 0 to 5 px (default 0: the "
                        "ray histogram; 0.4714, the paper's sqrt(2)/3, smooths the ray grid's moire that differs "
                        "between ray counts)")
    t.add_argument("--rays", type=positive_int, default=64, help="pupil samples per side (PSF settings)")
    t.add_argument("--wavelengths", type=positive_int, default=31, help="wavelengths per PSF")
    t.add_argument("--fields", type=positive_int, default=64, help="library fields")
    t.add_argument("--depths", type=positive_int, default=20, help="library depth bins (plus infinity)")
    t.add_argument("--focus-lens", action="append", help="radial: learn this lens across focus distances")
    t.add_argument("--focus-range", type=float, nargs=2, default=(0.7, math.inf), metavar=("NEAR", "FAR"),
                   help="focus distances learned (m, FAR may be inf; default 0.7 inf); the prescribed focus "
                        "is learned besides")
    t.add_argument("--focus-bins", type=positive_int, default=3,
                   help="PSF libraries per focus lens, uniform in diopters over the focus range (default 3; "
                        "each is one library build), plus the prescribed one")
    t.add_argument("--seed", type=int, default=0, help="seed of weights, sampling and traced points")


def add_commands(sub) -> None:
    q = sub.add_parser("olf", help="Omni-Lens-Field: a network of a lens's PSFs (train, points, info)",
                       description="Omni-Lens-Field: one small network for the PSFs of several lenses, "
                                   "trained on their ray-traced PSFs, served without torch. " + UNITS)
    osub = add_subcommands(q, "olf_command")
    t = osub.add_parser("train", help="train (or resume) an OLF and export it to .npz",
                        description="Train an Omni-Lens-Field (CPU, seeded) and export it. Checkpoints go "
                                    "to the run folder; the same command again resumes a killed run and "
                                    "ends where an uninterrupted one would.")
    t.add_argument("--lens", action="append", required=True, help="lens id (repeat for several)")
    t.add_argument("--variant", choices=["radial", "paper"], default="radial",
                   help="radial (field radius, inverse depth, per-lens k; ours) or paper (the paper's MLP)")
    t.add_argument("--size", default="tiny", help="tiny, small, medium, large or paper (N=5, W=2048)")
    t.add_argument("--iters", type=positive_int, default=1000, help="iterations (the paper: 600000)")
    t.add_argument("--batch", type=positive_int, default=256, help="batch size (default 256)")
    t.add_argument("--lr", type=float, default=1e-4, help="initial learning rate (cosine to 1e-7)")
    t.add_argument("--threads", type=positive_int, default=None, help="torch threads (default: all cores)")
    add_device_option(t)
    t.add_argument("-o", "--output", required=True, help="the exported OLF (.npz)")
    t.add_argument("--run", default=None, help="run folder for checkpoints (default OUTPUT.run)")
    t.add_argument("--checkpoint-every", type=positive_int, default=500, help="iterations between checkpoints")
    t.add_argument("--validate-every", type=int, default=0, metavar="N",
                   help="score the held-out points every N iterations into the run's log.jsonl: the learning "
                        "curve (default 0: at the end only)")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights to export")
    t.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="how the exported weights are stored (float16 halves the file; the runtime computes in "
                        "float32 and the held-out figures printed are the stored file's)")
    _add_data_options(t)
    t.set_defaults(func=cmd_olf_train)
    pt = osub.add_parser("points", help="the traced off-grid and held-out points of a training config (no training)",
                         description="Trace (or read from the PSF cache) what `olf train` with the same data "
                                     "options would train and validate on, into a points file: e.g. the held-out "
                                     "points of an older OLF, for `python -m lab report olf --held-out-points`.")
    pt.add_argument("--lens", action="append", required=True, help="lens id (repeat; the order decides the seeds)")
    pt.add_argument("-o", "--output", required=True, help="the points file (.npz)")
    _add_data_options(pt)
    pt.set_defaults(func=cmd_olf_points)
    i = osub.add_parser("info", help="what an exported OLF holds: lenses, sizes, held-out figures")
    i.add_argument("file", nargs="*", help="exported OLF files (.npz); default: the shipped ones")
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=cmd_olf_info)
