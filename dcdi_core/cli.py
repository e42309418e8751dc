"""The `dcdi` command.

Units everywhere: lengths of lenses in millimetres, depths (object distances
from the lens's first vertex) in metres (`inf` for infinity), wavelengths in
nanometres, angles in degrees, fields as normalised image height (1 = sensor
semi-diagonal).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

UNITS = ("units: lens lengths in mm; depth D in metres from the lens's first vertex "
         "('inf' for infinity); wavelengths in nm; angles in degrees; field F is the "
         "normalised image height (1 = sensor semi-diagonal).")


def _depth(text: str) -> float:
    if text.strip().lower() in ("inf", "infinity"):
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"depth must be a number of metres or 'inf', got {text!r}")
    if not v > 0:
        raise argparse.ArgumentTypeError(f"depth must be > 0 metres (or 'inf'), got {text!r}")
    return v


def _focus(text: str):
    """A focus distance in metres, 'inf', or 'prescribed' (the lens as its prescription stands)."""
    if text.strip().lower() == "prescribed":
        return "prescribed"
    return _depth(text)


def _positive_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def _dump(obj) -> str:
    def fix(o):
        if isinstance(o, float) and not math.isfinite(o):
            return "inf" if o > 0 else ("-inf" if o < 0 else None)
        if isinstance(o, dict):
            return {k: fix(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [fix(v) for v in o]
        return o
    return json.dumps(fix(obj), indent=2)


# ------------------------------------------------------------------ commands
def cmd_lens_list(args) -> int:
    from .optics.lens import available_lenses, load_lens
    for lid in available_lenses():
        lens = load_lens(lid)
        print(f"{lid:<14} {lens.name}  ({lens.path})")
    return 0


def cmd_lens_info(args) -> int:
    from .optics.lens import load_lens
    from .optics.report import format_info, lens_info
    lens = load_lens(args.lens)
    info = lens_info(lens, args.wavelength, real_rays=not args.paraxial_only)
    print(_dump(info) if args.json else format_info(info))
    return 0


def cmd_lens_import(args) -> int:
    from .optics.lens import Lens
    from .optics.zemax import read_zmx, write_toml
    d = read_zmx(args.file)
    if args.id:
        d["id"] = args.id
    Lens.from_dict(d, args.file)           # validate before anything is written
    write_toml(d, args.output)
    print(f"wrote {args.output} ({len(d['surface'])} surfaces)")
    return 0


def cmd_spot(args) -> int:
    import numpy as np
    from .optics.analysis import spot_diagram
    from .optics.lens import load_lens
    lens = load_lens(args.lens)
    kw = {"field": [args.field]} if args.field is not None else {"angle_deg": [args.angle]}
    s = spot_diagram(lens, [args.depth], [args.wavelength], rays=args.rays, **kw)
    res = {
        "lens": lens.id,
        "depth_m": args.depth,
        "wavelength_nm": args.wavelength,
        "field": args.field,
        "angle_deg": float(np.degrees(np.arctan(s.aimed.p[0, 0]))),
        "rays": args.rays,
        "rays_in_stop": s.n_pupil,
        "chief_ray_ok": bool(s.aimed.ok[0, 0]),
        "chief_ray_height_mm": float(s.chief_y_mm[0, 0, 0]),
        "centroid_mm": [float(v) for v in s.centroid_mm[0, 0, 0]],
        "rms_radius_mm": float(s.rms_radius_mm[0, 0, 0]),
        "vignetted_fraction": float(s.vignetted_fraction[0, 0, 0]),
        "ray_status": s.bundle.counts(),
        "aim_residual_mm": s.aim_residual_mm,
    }
    if args.json:
        print(_dump(res))
    else:
        for k, v in res.items():
            print(f"{k:<22} {v}")
    return 0


def _psf_settings(args, *, focus: bool = True):
    """PSF settings from the common options; ``focus``: read --focus as the
    sensor's focus (bokeh's --focus means more and is read there)."""
    from .psf.compute import PSFSettings
    base = PSFSettings()
    sigma = getattr(args, "deposit_sigma", None)
    return PSFSettings(kernel_size=args.kernel or base.kernel_size,
                       pupil_samples=args.rays or base.pupil_samples,
                       n_wavelengths=args.wavelengths or base.n_wavelengths,
                       precision=args.precision or base.precision,
                       deposit_sigma_px=base.deposit_sigma_px if sigma is None else sigma,
                       pixel_pitch_mm=args.pixel_pitch,
                       focus_distance_m=getattr(args, "focus", None) if focus else None)


def _response(args):
    if getattr(args, "response", None):
        from .psf.spectral import load_response
        return load_response(args.response)
    return None


def _choose_psf_source(args, lens, *, pixel_pitch_mm, settings, focus_m, extra_reason=None):
    """The PSF source of a psf / simulate / bokeh request (``--psf-source``,
    ``--olf``): the OLF where it covers the request, else tracing; says which
    and why on standard error (one line)."""
    from .models.errors import ModelError
    from .models.runtime.library import PSFSource, psf_source
    if extra_reason is not None and args.psf_source != "trace":
        if args.psf_source == "olf":
            raise ModelError(f"--psf-source olf: the Omni-Lens-Field cannot serve this request: {extra_reason}")
        src = PSFSource("trace", f"PSFs traced: {extra_reason}")
    else:
        src = psf_source(lens, source=args.psf_source, olf_file=args.olf, pixel_pitch_mm=pixel_pitch_mm,
                         settings=settings, kernel_size=args.kernel, focus_m=focus_m,
                         custom_response=args.response is not None)
    print(f"dcdi: {src.message}", file=sys.stderr)
    return src


def _psf_from_olf(args, lens, src, settings):
    """``dcdi psf`` served by the OLF: (kernel (3, k, k), pixel pitch), or
    None where the request lies outside its ranges (then traced, said why)."""
    from .models.errors import ModelError, OutsideTrainedRangeError
    try:
        kernel = src.library.olf.psf(lens, args.field, args.depth, settings.focus_distance_m)
    except OutsideTrainedRangeError as e:
        if args.psf_source == "olf":
            raise ModelError(f"--psf-source olf: the Omni-Lens-Field cannot serve this request: {e}") from None
        print(f"dcdi: PSFs traced instead: {e}", file=sys.stderr)
        return None
    return kernel.astype("float32"), src.library.pixel_pitch_mm


def cmd_psf(args) -> int:
    import numpy as np
    from .atomic import atomic_path
    from .optics.lens import load_lens
    from .psf.compute import pixel_pitch_mm, psf
    from .psf.plots import depth_label, psf_grid_png
    lens = load_lens(args.lens)
    settings = _psf_settings(args)
    extra = ("a field angle (--angle) was given; the OLF takes a field (--field)" if args.angle is not None else
             f"a monochromatic kernel (--wavelength {args.wavelength:g}) was asked for; the OLF learned the "
             "visible band" if args.wavelength is not None else None)
    src = _choose_psf_source(args, lens, pixel_pitch_mm=pixel_pitch_mm(lens, settings), settings=settings,
                             focus_m=settings.focus_distance_m, extra_reason=extra)
    served = _psf_from_olf(args, lens, src, settings) if src.kind == "olf" else None
    if served is not None:
        kernel, pitch = served
        k = kernel.shape[-1]
        res = {"lens": lens.id, "depth_m": args.depth, "field": args.field, "kernel_size": k,
               "pixel_pitch_mm": pitch, "psf_source": "olf", "olf_file": src.olf_file,
               "channel_sums": [float(v) for v in kernel.sum(axis=(-1, -2))]}
        if args.out:
            with atomic_path(args.out) as tmp:
                with open(tmp, "wb") as f:
                    np.savez(f, psf=kernel, pixel_pitch_mm=np.float64(pitch))
        if args.png:
            psf_grid_png(kernel[None, None], [f"field {args.field}"], [depth_label(args.depth)], args.png,
                         f"{lens.name} (OLF)", pitch)
        print(_dump(res) if args.json else "\n".join(f"{k_:<22} {v}" for k_, v in res.items()))
        return 0
    r = psf(lens, depth_m=args.depth, field=args.field, angle_deg=args.angle, settings=settings,
            response=_response(args), wavelength_nm=args.wavelength)
    pitch = pixel_pitch_mm(lens, settings)
    if r.zero_energy:
        print("dcdi: error: no ray of this field reaches the sensor (fully vignetted or beyond the "
              "image circle); the kernel would be empty", file=sys.stderr)
        return 2
    res = {
        "lens": lens.id, "depth_m": args.depth, "field": args.field, "angle_deg": args.angle,
        "wavelength_nm": args.wavelength, "kernel_size": settings.kernel_size, "pixel_pitch_mm": pitch,
        "chief_ray_height_mm": float(r.chief_ray_height_mm),
        "relative_illumination": float(r.relative_illumination),
        "energy_outside": float(r.energy_outside.max()), "psf_source": "trace",
    }
    for c, name in enumerate("RGB"):
        res[name] = {"centroid_mm": [float(v) for v in r.centroid_mm[c]],
                     "rms_radius_mm": float(r.rms_radius_mm[c]),
                     "energy_outside": float(r.energy_outside[c]),
                     "vignetted_fraction": float(r.vignetted_fraction[c])}
    if args.out:
        with atomic_path(args.out) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, psf=r.psf, pixel_pitch_mm=np.float64(pitch))
    if args.png:
        where = f"field {args.field}" if args.field is not None else f"{args.angle} deg"
        psf_grid_png(r.psf[None, None], [where], [depth_label(args.depth)], args.png,
                     f"{lens.name}", pitch)
    print(_dump(res) if args.json else "\n".join(f"{k:<22} {v}" for k, v in res.items()))
    return 0


def cmd_psflib_build(args) -> int:
    from .optics.lens import load_lens
    from .psf.library import LibraryGrid, PSFLibrary, text_progress
    lens = load_lens(args.lens)
    grid = LibraryGrid(n_fields=args.fields, n_depths=args.depths, near_m=args.near, far_m=args.far)
    lib = PSFLibrary.open(lens, _psf_settings(args), grid, _response(args), cache=not args.no_cache)
    t = time.perf_counter()
    done = lib.build(progress=text_progress(f"psflib {lens.id}"))
    lib.save(args.output)
    print(f"wrote {args.output}: {len(lib.depths_m)} depth bins x {len(lib.fields)} fields x 3 x "
          f"{lib.kernel_size} x {lib.kernel_size}; computed {len(done)} bins in "
          f"{time.perf_counter() - t:.1f} s ({len(lib.depths_m) - len(done)} from the cache)")
    return 0


def cmd_psflib_show(args) -> int:
    import math
    import numpy as np
    from .optics.lens import load_lens
    from .psf.library import PSFLibrary
    from .psf.plots import depth_label, psf_grid_png
    if args.library.endswith(".npz"):
        lib = PSFLibrary.load(args.library)
    else:
        lib = PSFLibrary.open(load_lens(args.library), _psf_settings(args))
    fields = np.array(args.show_fields)
    depths = np.array(args.show_depths)
    if lib.lens is None:   # a file: show the bins it holds, nearest to what was asked
        keep = np.flatnonzero(lib.computed)
        di = [int(keep[np.argmin(np.abs(lib.diopters[keep] - (0 if math.isinf(d) else 1 / d)))]) for d in depths]
        fi = [int(np.argmin(np.abs(lib.fields - f))) for f in fields]
        kernels = lib.psf[np.ix_(di, fi)].swapaxes(0, 1)
        depths, fields = lib.depths_m[di], lib.fields[fi]
    else:
        kernels = lib.at(fields[:, None], depths[None, :], clamp_near=False)
    psf_grid_png(kernels, [f"field {f:.2f}" for f in fields], [depth_label(d) for d in depths],
                 args.png, f"PSF library: {lib.meta['lens_id']}", lib.pixel_pitch_mm)
    print(f"wrote {args.png}")
    return 0


def _read_rgbd(args):
    from .io.images import read_depth, read_image
    img = read_image(args.image)
    depth = read_depth(args.depth)
    if depth.shape != img.shape[:2]:
        from .optics.errors import InputRangeError
        raise InputRangeError(f"depth map {args.depth}", depth.shape, f"{img.shape[:2]} (the image {args.image})")
    return img, depth


def _image_pitch(args):
    """The image's pixel pitch (mm) from --image-pixel-pitch or --pixel-pitch
    (the same thing here: PSFs are sampled at the image's pitch)."""
    from .optics.errors import InputRangeError
    a, b = args.image_pixel_pitch, args.pixel_pitch
    if a is not None and b is not None and a != b:
        raise InputRangeError("--pixel-pitch", b, f"--image-pixel-pitch's {a} mm, or leave one out (the PSFs of "
                              "an image are sampled at its own pitch)")
    pitch = a if a is not None else b
    if pitch is not None and not (pitch > 0 and math.isfinite(pitch)):
        raise InputRangeError("--image-pixel-pitch", pitch, "a pixel pitch > 0 mm")
    return pitch


def _geometries(args, lens, shape):
    """(sensor geometry, source geometry or None) from --image-pixel-pitch,
    --sensor-size and --axis; checked before any work."""
    from .optics.errors import InputRangeError
    from .render.geometry import ImageGeometry
    from .render.simulate import check_within_sensor
    h, w = shape
    pitch = _image_pitch(args)
    axis = tuple(args.axis) if args.axis else None
    if axis is not None and not (-0.5 <= axis[0] <= h - 0.5 and -0.5 <= axis[1] <= w - 0.5):
        raise InputRangeError("--axis", axis, f"a pixel position (row, col) inside the {h} x {w} image")
    if args.sensor_size is None:
        if pitch is None:
            if axis is not None:
                raise InputRangeError("--axis", axis, "only with --image-pixel-pitch or --sensor-size (without "
                                      "them the image spans the sensor's diagonal about its centre)")
            return ImageGeometry.full_sensor(lens, h, w), None
        geom = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=axis)
        check_within_sensor(geom, f"the image {args.image}")
        return geom, None
    rows, cols = args.sensor_size
    if rows > h or cols > w:
        raise InputRangeError("--sensor-size", (rows, cols), f"at most the image's {h} x {w} pixels (the sensor's "
                              f"frame inside an over-scan render of {args.image})")
    if pitch is None:        # the sensor's frame spans the lens's sensor diagonal
        pitch = ImageGeometry.full_sensor(lens, rows, cols).pixel_pitch_mm
    sensor = ImageGeometry.from_pixel_pitch(lens, rows, cols, pitch)
    check_within_sensor(sensor, "--sensor-size")
    source = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=axis)
    return sensor, source


def _render_inputs(args):
    """Everything simulate and bokeh check before any work: the lens, the
    output paths, the response file, the images and the geometry."""
    from .io.images import check_image_output
    from .optics.lens import load_lens
    lens = load_lens(args.lens)
    for path in (args.output, getattr(args, "sharp_out", None)):
        if path:
            check_image_output(path)
    from dataclasses import replace
    settings = replace(_psf_settings(args, focus=args.command != "bokeh"), pixel_pitch_mm=None,
                       wavelength_nm=args.wavelength)
    response = _response(args)
    img, depth = _read_rgbd(args)
    geom, source = _geometries(args, lens, img.shape[:2])
    from .render.simulate import check_patch
    check_patch(args.patch)
    from .render.distortion import check_interpolation
    check_interpolation(args.interpolation)
    return lens, settings, response, img, depth, geom, source


def cmd_simulate(args) -> int:
    from .io.images import write_image
    from .render.simulate import LensSimulator
    lens, settings, response, img, depth, geom, source = _render_inputs(args)
    record = None
    if args.perturb is not None:
        from .optics.perturb import perturb_lens
        lens, record = perturb_lens(lens, seed=args.perturb, fraction=args.perturb_fraction)
    noise = {"full_well_electrons": args.full_well, "read_noise_electrons": args.read_noise} if args.noise else None
    if noise is not None and args.seed is None:
        from .optics.errors import InputRangeError
        raise InputRangeError("--seed", None, "an integer: --noise needs an explicit seed")
    src = _choose_psf_source(args, lens, pixel_pitch_mm=geom.pixel_pitch_mm, settings=settings,
                             focus_m=settings.focus_distance_m)
    # without --kernel, the kernel grows to hold the PSFs this depth map needs
    # (an OLF's kernels hold 99 % of the energy over its whole depth range)
    sim = LensSimulator(lens, geom, source_geometry=source, settings=settings, library=src.library,
                        response=response, patch=args.patch, distortion=not args.no_distortion,
                        interpolation=args.interpolation, fit_depth_m=None if args.kernel else depth)
    r = sim(img, depth, fixed_depth_m=args.fixed_depth, noise=noise, seed=args.seed)
    write_image(args.output, r.image)
    if args.sharp_out:
        write_image(args.sharp_out, r.sharp)
    print(_dump({"output": args.output, **r.info, "perturbation": record, "psf_source": src.kind,
                 "olf_file": src.olf_file if src.kind == "olf" else None}))
    return 0


def cmd_bokeh(args) -> int:
    from .io.images import write_image
    from .render.simulate import bokeh
    lens, settings, response, img, depth, geom, source = _render_inputs(args)
    keep = tuple(args.keep) if args.keep else None
    focus_m = None if args.focus in (None, "prescribed") else args.focus
    src = _choose_psf_source(args, lens, pixel_pitch_mm=geom.pixel_pitch_mm, settings=settings, focus_m=focus_m)
    r = bokeh(img, depth, lens, keep=keep, focus_m=args.focus, geometry=geom, source_geometry=source,
              distortion=args.distort, interpolation=args.interpolation, patch=args.patch,
              occlusion=not args.plain, settings=settings, response=response, fit_kernel=not args.kernel,
              library=src.library)
    write_image(args.output, r.image)
    if args.side_by_side:
        from .render.pictures import side_by_side
        what = (f"keep {keep[0]:g}-{keep[1]:g} m" if keep else
                "as prescribed" if args.focus == "prescribed" else f"focus {args.focus:g} m")
        side_by_side(args.side_by_side, img if r.sharp is None else r.sharp,
                     depth if r.depth is None else r.depth, r.image, f"{lens.name}: {what}")
    print(_dump({"output": args.output, **r.info, "psf_source": src.kind,
                 "olf_file": src.olf_file if src.kind == "olf" else None}))
    return 0


def cmd_report(args) -> int:
    from .psf.accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_sim(args) -> int:
    from .render.accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_olf(args) -> int:
    from .models.report import run_report
    return run_report(args.olf, args.out, quick=args.quick, sweep=args.sweep)


def cmd_bench(args) -> int:
    from . import bench
    return bench.run(args.what, args)


def cmd_demo(args) -> int:
    from . import demo
    return demo.run(args.out)


# ------------------------------------------------------- olf (dcdi_core.models)
def cmd_olf_train(args) -> int:
    import os
    from pathlib import Path
    from .models.data.psf_samples import PSFDataConfig
    from .models.train.config import OLFTrainConfig
    data = PSFDataConfig(lenses=tuple(args.lens), variant=args.variant, pupil_samples=args.rays,
                         n_wavelengths=args.wavelengths, n_fields=args.fields, n_depths=args.depths,
                         focus_lenses=tuple(args.focus_lens or ()), focus_range_m=tuple(args.focus_range),
                         offgrid=args.offgrid, held_out=args.held_out, seed=args.seed)
    config = OLFTrainConfig(data=data, size=args.size, iters=args.iters, batch=args.batch, lr=args.lr,
                            seed=args.seed, threads=args.threads or (os.cpu_count() or 1),
                            checkpoint_every=args.checkpoint_every)
    from .models.export import export_olf               # torch from here on
    from .models.train.loop import train
    run = Path(args.run or (str(args.output) + ".run"))
    tty = sys.stderr.isatty()
    bar = None

    t_start = time.perf_counter()

    def progress(step, total, loss):
        nonlocal bar
        if not tty:           # a log file: one line per checkpoint
            if step % config.checkpoint_every == 0 or step == total:
                print(f"olf train: iteration {step}/{total}, loss {loss:.3g}, "
                      f"{time.perf_counter() - t_start:.0f} s since start", file=sys.stderr, flush=True)
            return
        if bar is None:             # made at the first step, so that its rate is the training's
            try:
                from tqdm import tqdm
            except ImportError:     # no bar without tqdm (requirements.txt has it)
                return
            bar = tqdm(total=total, initial=step - 1, desc="olf train", unit="it", file=sys.stderr,
                       dynamic_ncols=True)
        bar.set_postfix(loss=f"{loss:.3g}", refresh=False)
        bar.update(step - bar.n)

    def log(text):
        print(f"{text} ({time.perf_counter() - t_start:.0f} s since start)", file=sys.stderr, flush=True)
    try:
        result = train(config, run, progress=progress, log=log)
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        print(f"dcdi: interrupted; the last checkpoint is in {run}: run the same command to resume",
              file=sys.stderr)
        return 130
    if bar is not None:
        bar.close()
    meta = export_olf(result, args.output, weights=args.weights, dtype=args.dtype)
    h = meta["held_out"]["mean"]
    rate = result.step / result.seconds if result.seconds > 0 else float("nan")
    print(f"wrote {args.output} ({meta['parameters']} parameters, {os.path.getsize(args.output)} bytes; "
          f"run folder {run})")
    print(f"held-out ({args.weights}): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM "
          + (f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a")
          + f", relative L1 {h['rel_l1']:.4f}; {result.seconds:.1f} s of training ({rate:.1f} it/s; PSF data not included)")
    return 0


def cmd_olf_info(args) -> int:
    from .models.runtime.library import WEIGHTS_DIR, shipped_olf_files
    from .models.runtime.olf import OmniLensField
    from .optics.lens import load_lens
    files = args.file or shipped_olf_files()
    if not files:
        print(f"no OLF file ships with this engine ({WEIGHTS_DIR} holds none); give one: dcdi olf info FILE.npz")
        return 0
    infos = []
    for path in files:
        olf = OmniLensField.load(path)
        info = olf.info()
        info["shipped"] = not args.file
        for entry in info["lenses"]:
            try:
                entry["prescription"] = "current" if olf.covers(load_lens(entry["id"])) else "differs (not served)"
            except Exception as e:  # noqa: BLE001 - a lens that no longer loads is reported, not fatal
                entry["prescription"] = f"not loadable ({e})"
        infos.append(info)
    if args.json:
        print(_dump(infos[0] if args.file and len(infos) == 1 else infos))
        return 0
    for info in infos:
        _print_olf_info(info)
    return 0


def _print_olf_info(info) -> None:
    print(f"{info['file']}{' (shipped)' if info.get('shipped') else ''}: {info['variant']} Omni-Lens-Field, "
          f"{info['hidden_layers']} hidden layers x {info['width']}, {info['parameters']} parameters "
          f"({info['dtype']}, {info['weights']} weights), {info['bytes']} bytes")
    per = ((info["held_out"] or {}).get("lenses")) or {}
    for e in info["lenses"]:
        focus = f", focus {e['focus_range_m']} m" if e["focus_range_m"] else ""
        h = per.get(e["id"])
        fig = (f"; held-out {h['psnr_8bit']:.2f} dB, SSIM "
               + (f"{h['ssim_8bit']:.4f}" if h.get("ssim_8bit") is not None else "n/a")
               + f", rel. L1 {h['rel_l1']:.4f}") if h else ""
        print(f"  {e['id']:<14} k = {e['kernel_size']}, pitch {e['pixel_pitch_mm'] * 1000:.3g} um, "
              f"depth {e['depth_range_m'][0]}-{e['depth_range_m'][1]} m{focus}; prescription "
              f"{e['prescription']}{fig}")
    h = (info["held_out"] or {}).get("mean")
    if h:
        ssim = f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a"
        print(f"  held-out (mean over lenses): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM {ssim}, "
              f"relative L1 {h['rel_l1']:.4f}, PSNR {h['psnr_sum']:.2f} dB (sum-normalised)")
    t = info["training"] or {}
    if t:
        print(f"  trained {t.get('iterations')} iterations in {t.get('seconds', 0):.0f} s; checksum "
              f"{info['checksum'][:16]}...")


def add_olf_commands(sub) -> None:
    """`dcdi olf train|info`: the Omni-Lens-Field (torch only for training)."""
    q = sub.add_parser("olf", help="Omni-Lens-Field: a network of a lens's PSFs (train, info)",
                       description="Omni-Lens-Field: one small network for the PSFs of several lenses, "
                                   "trained on their ray-traced PSFs, served without torch. " + UNITS)
    osub = q.add_subparsers(dest="olf_command", required=True, metavar="SUBCOMMAND")
    t = osub.add_parser("train", help="train (or resume) an OLF and export it to .npz",
                        description="Train an Omni-Lens-Field (CPU, seeded) and export it. Checkpoints go "
                                    "to the run folder; the same command again resumes a killed run and "
                                    "ends where an uninterrupted one would.")
    t.add_argument("--lens", action="append", required=True, help="lens id (repeat for several)")
    t.add_argument("--variant", choices=["radial", "paper"], default="radial",
                   help="radial (field radius, inverse depth, per-lens k; ours) or paper (the paper's MLP)")
    t.add_argument("--size", default="tiny", help="tiny, small, medium, large or paper (N=5, W=2048)")
    t.add_argument("--iters", type=_positive_int, default=1000, help="iterations (the paper: 600000)")
    t.add_argument("--batch", type=_positive_int, default=256, help="batch size (default 256)")
    t.add_argument("--lr", type=float, default=1e-4, help="initial learning rate (cosine to 1e-7)")
    t.add_argument("--seed", type=int, default=0, help="seed of weights, sampling and traced points")
    t.add_argument("--threads", type=_positive_int, default=None, help="torch threads (default: all cores)")
    t.add_argument("-o", "--output", required=True, help="the exported OLF (.npz)")
    t.add_argument("--run", default=None, help="run folder for checkpoints (default OUTPUT.run)")
    t.add_argument("--checkpoint-every", type=_positive_int, default=500, help="iterations between checkpoints")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights to export")
    t.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="how the exported weights are stored (float16 halves the file; the runtime computes in "
                        "float32 and the held-out figures printed are the stored file's)")
    t.add_argument("--offgrid", type=int, default=256, help="traced off-grid training points per lens")
    t.add_argument("--held-out", type=_positive_int, default=64, help="traced held-out points per lens")
    t.add_argument("--rays", type=_positive_int, default=64, help="pupil samples per side (PSF settings)")
    t.add_argument("--wavelengths", type=_positive_int, default=31, help="wavelengths per PSF")
    t.add_argument("--fields", type=_positive_int, default=64, help="library fields")
    t.add_argument("--depths", type=_positive_int, default=20, help="library depth bins (plus infinity)")
    t.add_argument("--focus-lens", action="append", help="radial: learn this lens across focus distances")
    t.add_argument("--focus-range", type=float, nargs=2, default=(0.7, 10.0), metavar=("NEAR", "FAR"),
                   help="focus distances learned (m, default 0.7 10)")
    t.set_defaults(func=cmd_olf_train)
    i = osub.add_parser("info", help="what an exported OLF holds: lenses, sizes, held-out figures")
    i.add_argument("file", nargs="*", help="exported OLF files (.npz); default: the shipped ones")
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=cmd_olf_info)


# ------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dcdi", description=__doc__.split("\n\n")[0] + " " + UNITS,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    lens = sub.add_parser("lens", help="lens prescriptions: list, info, import",
                          description="Lens prescriptions. " + UNITS)
    lsub = lens.add_subparsers(dest="lens_command", required=True, metavar="SUBCOMMAND")
    q = lsub.add_parser("list", help="the lenses found in lenses/ (and $DCDI_LENS_PATH)")
    q.set_defaults(func=cmd_lens_list)
    q = lsub.add_parser("info", help="first-order and real-ray properties of a lens",
                        description="EFL, BFL, F-number, pupils, in-focus distance, field of view. " + UNITS)
    q.add_argument("lens", help="lens id (e.g. mos-s1) or path to a .toml file")
    q.add_argument("--wavelength", type=float, default=None, metavar="NM",
                   help="wavelength in nm (default: the lens's design wavelength, 587.56 nm)")
    q.add_argument("--json", action="store_true", help="print JSON")
    q.add_argument("--paraxial-only", action="store_true", help="skip the real-ray figures (faster)")
    q.set_defaults(func=cmd_lens_info)
    q = lsub.add_parser("import", help="import a Zemax .zmx file (STANDARD and EVENASPH surfaces)")
    q.add_argument("file", help="the .zmx file")
    q.add_argument("-o", "--output", required=True, help="the .toml file to write")
    q.add_argument("--id", help="lens id to give (default: from the file name)")
    q.set_defaults(func=cmd_lens_import)

    q = sub.add_parser("spot", help="spot diagram statistics of one field, depth and wavelength",
                       description="Trace an N x N square grid over the real stop, with ray aiming, "
                                   "and report on the sensor plane. " + UNITS)
    q.add_argument("lens", help="lens id or .toml path")
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--field", type=float, metavar="F", help="normalised image height (1 = sensor semi-diagonal)")
    g.add_argument("--angle", type=float, metavar="DEG", help="field angle in object space, degrees")
    q.add_argument("--depth", type=_depth, required=True, metavar="D", help="object depth in metres, or inf")
    q.add_argument("--wavelength", type=float, required=True, metavar="NM", help="wavelength in nm")
    q.add_argument("--rays", type=_positive_int, default=128, metavar="N", help="pupil grid N x N (default 128)")
    q.add_argument("--json", action="store_true", help="print JSON")
    q.set_defaults(func=cmd_spot)

    def psf_options(q, focus=True, render=False):
        from .psf.compute import PSFSettings
        d = PSFSettings()
        grows = "; without this option it grows to hold the depth map's blur, up to 129" if render else ""
        q.add_argument("--kernel", type=_positive_int, default=None, metavar="K",
                       help=f"kernel size K x K px, odd (default {d.kernel_size}{grows})")
        q.add_argument("--deposit-sigma", type=float, default=None, metavar="PX",
                       help=f"Gaussian spread of each ray in pixels on top of the pixel it lands in (default "
                            f"{d.deposit_sigma_px:g}: what a sensor records; the paper's 0.471 blurs)")
        q.add_argument("--rays", type=_positive_int, default=None, metavar="N",
                       help=f"pupil grid N x N over the real stop (default {d.pupil_samples})")
        q.add_argument("--wavelengths", type=_positive_int, default=None, metavar="W",
                       help=f"wavelength samples over 400-700 nm (default {d.n_wavelengths})")
        q.add_argument("--precision", choices=["float32", "float64"], default=None,
                       help=f"ray tracing precision (default {d.precision})")
        q.add_argument("--pixel-pitch", type=float, default=None, metavar="MM",
                       help="pixel pitch in mm (default: the lens's sensor)")
        if focus:
            q.add_argument("--focus", type=_depth, default=None, metavar="D",
                           help="move the sensor to focus depth D metres (default: as prescribed)")
        q.add_argument("--response", default=None, metavar="CSV",
                       help="sensor spectral response CSV (wavelength_nm,r,g,b); default: shipped curves")

    def psf_source_options(q):
        q.add_argument("--psf-source", choices=["olf", "trace"], default=None,
                       help="where the PSFs come from: the Omni-Lens-Field (an error if it cannot serve the "
                            "request) or ray tracing; default: the OLF where it covers the lens (its learned "
                            "prescription) and the request (depth range, pixel pitch, focus, PSF settings), "
                            "else tracing; a line on standard error says which and why")
        q.add_argument("--olf", default=None, metavar="FILE.npz",
                       help="the OLF file to serve PSFs from (default: the one shipped in dcdi_core/models/weights)")

    q = sub.add_parser("psf", help="the RGB PSF of one field and depth",
                       description="RGB PSF on the sensor's pixel grid, centred on the chief ray. " + UNITS)
    q.add_argument("lens", help="lens id or .toml path")
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--field", type=float, metavar="F", help="normalised image height (1 = sensor semi-diagonal)")
    g.add_argument("--angle", type=float, metavar="DEG", help="field angle in object space, degrees")
    q.add_argument("--depth", type=_depth, required=True, metavar="D", help="object depth in metres, or inf")
    q.add_argument("--wavelength", type=float, default=None, metavar="NM",
                   help="monochromatic kernel at NM nm (all three channels alike)")
    q.add_argument("--out", default=None, metavar="FILE.npz", help="write psf (3,k,k) and pixel_pitch_mm")
    q.add_argument("--png", default=None, metavar="FILE.png", help="write a picture of the kernel")
    q.add_argument("--json", action="store_true", help="print JSON")
    psf_options(q)
    psf_source_options(q)
    q.set_defaults(func=cmd_psf)

    q = sub.add_parser("psflib", help="PSF libraries (fields x depths): build, show")
    psub = q.add_subparsers(dest="psflib_command", required=True, metavar="SUBCOMMAND")
    b = psub.add_parser("build", help="build a lens's PSF library and write it to a file",
                        description="Depth bins uniform in 1/depth from --near to --far, plus infinity. " + UNITS)
    b.add_argument("lens", help="lens id or .toml path")
    b.add_argument("-o", "--output", required=True, metavar="FILE.npz", help="the library file to write")
    b.add_argument("--fields", type=_positive_int, default=64, help="fields over [0, 1] (default 64)")
    b.add_argument("--depths", type=_positive_int, default=20, help="finite depth bins (default 20), plus infinity")
    b.add_argument("--near", type=float, default=0.7, metavar="M", help="nearest depth bin, metres (default 0.7)")
    b.add_argument("--far", type=float, default=10.0, metavar="M",
                   help="farthest finite bin, metres (default 10); farther = infinity")
    b.add_argument("--no-cache", action="store_true", help="do not read or write the cache")
    psf_options(b)
    b.set_defaults(func=cmd_psflib_build)
    s_ = psub.add_parser("show", help="a PNG grid of PSFs across field and depth")
    s_.add_argument("library", help="a library file (.npz from psflib build) or a lens id")
    s_.add_argument("--png", required=True, metavar="FILE.png")
    s_.add_argument("--show-fields", type=float, nargs="+", default=[0.0, 0.5, 0.7, 1.0], metavar="F")
    s_.add_argument("--show-depths", type=_depth, nargs="+", default=[0.7, 1.0, 2.0, 5.0, math.inf], metavar="D")
    psf_options(s_)
    s_.set_defaults(func=cmd_psflib_show)

    from .render.distortion import INTERPOLATIONS
    from .render.simulate import DEFAULT_INTERPOLATION

    def rgbd_options(q):
        q.add_argument("--image", required=True, help="all-in-focus image (EXR linear, or PNG/JPEG sRGB)")
        q.add_argument("--depth", required=True, help="metric depth map (EXR, metres from the lens; NaN/0/<0 invalid)")
        q.add_argument("--lens", required=True, help="lens id or .toml path")
        q.add_argument("-o", "--output", required=True, help="output image (.exr linear, or .png)")
        q.add_argument("--patch", type=_positive_int, default=16, help="patch size m in pixels (default 16)")
        q.add_argument("--image-pixel-pitch", type=float, default=None, metavar="MM",
                       help="size of one image pixel on the sensor (default: the image spans the sensor diagonal)")
        q.add_argument("--sensor-size", type=_positive_int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                       help="the sensor's frame in image pixels, centred on the optical axis, when the image is "
                            "larger (an over-scan render); the output has this size (default: the whole image)")
        q.add_argument("--axis", type=float, nargs=2, default=None, metavar=("ROW", "COL"),
                       help="the optical axis's pixel position in the image (default: its centre)")
        q.add_argument("--wavelength", type=float, default=None, metavar="NM",
                       help="one wavelength for all three channels (monochrome, narrow-band); default: the "
                            "visible band weighted by the sensor's response")
        q.add_argument("--interpolation", default=DEFAULT_INTERPOLATION, choices=INTERPOLATIONS,
                       help=f"how the distortion warp resamples the image (default {DEFAULT_INTERPOLATION})")
        psf_options(q, focus=q.prog.split()[-1] != "bokeh", render=True)
        psf_source_options(q)

    q = sub.add_parser("simulate", help="depth-aware aberration simulation of an all-in-focus RGB-D image",
                       description="Patch-wise depth-aware PSF convolution, lens distortion, optional noise. " + UNITS)
    rgbd_options(q)
    q.add_argument("--fixed-depth", type=_depth, default=None, metavar="D",
                   help="depth-unaware baseline: one depth D metres for the whole image")
    q.add_argument("--no-distortion", action="store_true", help="do not apply the lens's distortion")
    q.add_argument("--sharp-out", default=None, help="also write the sharp image, distorted alike (aligned pair)")
    q.add_argument("--noise", action="store_true", help="add shot and read noise (needs --seed)")
    q.add_argument("--full-well", type=float, default=10000.0, help="electrons at 1.0 (default 10000)")
    q.add_argument("--read-noise", type=float, default=3.0, help="read noise, electrons (default 3)")
    q.add_argument("--seed", type=int, default=None, help="random seed (noise)")
    q.add_argument("--perturb", type=int, default=None, metavar="SEED",
                   help="domain randomisation: perturb radii and thicknesses with this seed (recorded in the output)")
    q.add_argument("--perturb-fraction", type=float, default=0.10, metavar="F",
                   help="largest relative change of each perturbed value (default 0.10)")
    q.set_defaults(func=cmd_simulate)

    q = sub.add_parser("bokeh", help="the depth of field of a lens on an all-in-focus RGB-D image",
                       description="Keep a depth range sharp (--keep) or focus at a distance (--focus). " + UNITS)
    rgbd_options(q)
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--keep", type=float, nargs=2, metavar=("NEAR", "FAR"), help="depth range kept sharp, metres")
    g.add_argument("--focus", type=_focus, metavar="D",
                   help="focus the lens at D metres, or 'prescribed': the lens as its prescription stands "
                        "(full physical defocus everywhere)")
    q.add_argument("--distort", action="store_true", help="also apply the lens's distortion (before the blur)")
    q.add_argument("--plain", action="store_true", help="plain patch-wise blur instead of occlusion-aware layers")
    q.add_argument("--side-by-side", default=None, metavar="PNG", help="also write input | depth | result")
    q.set_defaults(func=cmd_bokeh)

    q = sub.add_parser("report", help="accuracy reports (error against run time)")
    rsub = q.add_subparsers(dest="report_command", required=True, metavar="REPORT")
    r = rsub.add_parser("psf-accuracy", help="PSF error vs build time for rays, wavelengths, bins, precision")
    r.add_argument("lens", help="lens id or .toml path")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown) and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="a smaller reference and sweep (for tests)")
    r.set_defaults(func=cmd_report)
    r = rsub.add_parser("simulation-accuracy", help="patch-wise simulation vs a per-pixel reference; bokeh at depth edges")
    r.add_argument("--lens", default="mos-s1", help="lens id (default mos-s1)")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown)")
    r.add_argument("--quick", action="store_true", help="a small image and sweep (for tests)")
    r.set_defaults(func=cmd_report_sim)
    r = rsub.add_parser("olf", help="Omni-Lens-Field: PSF error vs storage and time, PSF-map time, downstream images")
    r.add_argument("--olf", action="append", default=None, metavar="FILE.npz",
                   help="an OLF file (repeat for several; default: the shipped ones)")
    r.add_argument("--sweep", default=None, metavar="RESULTS.jsonl",
                   help="rows of the size x learning-rate sweep (out/sweep/results.jsonl) for the table and plot")
    r.add_argument("--out", default="out/report", help="folder for the table (Markdown), JSON and plot (PNG)")
    r.add_argument("--quick", action="store_true", help="few points and small images (for tests)")
    r.set_defaults(func=cmd_report_olf)

    q = sub.add_parser("bench", help="benchmarks (times, not tests)")
    q.add_argument("what", choices=["trace", "psflib", "render", "factory"], help="what to benchmark")
    q.add_argument("--rays", type=_positive_int, default=1 << 20, help="rays per trace (default 2^20)")
    q.add_argument("--repeat", type=_positive_int, default=3, help="timed repetitions (best is kept)")
    q.add_argument("--quick", action="store_true", help="psflib: a small library (for tests)")
    q.set_defaults(func=cmd_bench)

    q = sub.add_parser("demo", help="the demo job: lens reports and spot diagrams of all lenses")
    q.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    q.set_defaults(func=cmd_demo)

    add_olf_commands(sub)
    return p


def main(argv=None) -> int:
    from .optics.errors import OpticsError
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except OpticsError as e:
        print(f"dcdi: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
