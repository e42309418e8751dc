"""The `dcdi` command.

Units everywhere: lengths of lenses in millimetres, depths (object distances
from the lens's first vertex) in metres (`inf` for infinity), wavelengths in
nanometres, angles in degrees, fields as normalised image height (1 = sensor
semi-diagonal).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from pathlib import Path

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
    try:
        return _depth(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"focus must be a distance in metres (> 0), 'inf' or 'prescribed', "
                                         f"got {text!r}") from None


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


def _check_output(path, option: str, *, image: bool = False, suffix: str | None = None) -> None:
    """Refuse, before any work, an output that cannot be written: an image
    extension that is not supported (or not ``suffix``), a folder that is
    read-only or a file."""
    if not path:
        return
    from .errors import check_writable_folder
    if image:
        from .io.images import check_image_output
        check_image_output(path)
    if suffix is not None and not str(path).lower().endswith(suffix):
        from .errors import InputRangeError
        raise InputRangeError(option, str(path), f"a file name ending in {suffix} (what it writes)")
    from pathlib import Path
    check_writable_folder(Path(path).resolve().parent, f"{option} {path}")


def _check_cache(args=None) -> None:
    """Refuse, before any work, a PSF cache folder that cannot be written."""
    if args is not None and getattr(args, "no_cache", False):
        return
    from .errors import check_writable_folder
    from .psf.library import default_cache_dir
    check_writable_folder(default_cache_dir(), "the PSF cache (set DCDI_CACHE_DIR to a writable folder)")


def _check_wavelength(lens, args) -> None:
    if getattr(args, "wavelength", None) is not None:
        lens.check_wavelengths(args.wavelength, "--wavelength")


def _check_library_memory(settings, grid=None, *, map_kernels: int = 0) -> None:
    """Refuse, before any work, a PSF library that would not fit in memory."""
    from .psf.compute import check_psf_memory
    from .psf.library import LibraryGrid
    g = grid or LibraryGrid()
    n = g.n_fields * (g.n_depths + 1)
    check_psf_memory(settings, n, 1 if settings.wavelength_nm is not None else None, library_psfs=n,
                     map_kernels=map_kernels)


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
    _check_wavelength(lens, args)
    info = lens_info(lens, args.wavelength, real_rays=not args.paraxial_only)
    print(_dump(info) if args.json else format_info(info))
    return 0


def cmd_lens_import(args) -> int:
    from .optics.lens import Lens
    from .optics.zemax import read_zmx, write_toml
    _check_output(args.output, "-o", suffix=".toml")
    d = read_zmx(args.file)
    if args.id:
        d["id"] = args.id
    Lens.from_dict(d, args.file)           # validate before anything is written
    write_toml(d, args.output)
    print(f"wrote {args.output} ({len(d['surface'])} surfaces)")
    return 0


def _where(args):
    """(option, value) of the field asked for: --field or --angle."""
    return ("--field", args.field) if args.field is not None else ("--angle", args.angle)


def cmd_spot(args) -> int:
    import numpy as np
    from .optics.analysis import spot_diagram
    from .optics.lens import load_lens
    from .memory import check_fits
    from .psf.compute import BYTES_PER_RAY, stop_ray_count
    lens = load_lens(args.lens)
    _check_wavelength(lens, args)
    check_fits(stop_ray_count(args.rays) * BYTES_PER_RAY["float64"] * 2, f"spot --rays {args.rays} "
               f"({args.rays} x {args.rays} rays)", "lower --rays (memory grows as its square)")
    kw = {"field": [args.field]} if args.field is not None else {"angle_deg": [args.angle]}
    s = spot_diagram(lens, [args.depth], [args.wavelength], rays=args.rays, **kw)
    if not s.aimed.ok[0, 0] or s.vignetted_fraction[0, 0, 0] >= 1.0:
        from .errors import InputRangeError
        raise InputRangeError(*_where(args), "a field some ray of which reaches the sensor (no ray of this one "
                              "does: fully vignetted or beyond the image circle; no spot)")
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
        kernel = src.library.kernels(args.field, args.depth)     # at the request's pitch
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
    _check_output(args.out, "--out", suffix=".npz")
    _check_output(args.png, "--png", suffix=".png")
    _check_wavelength(lens, args)
    settings = _psf_settings(args)
    from .psf.compute import check_psf_memory
    check_psf_memory(settings, 1, 1 if args.wavelength is not None else None)
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
        from .errors import InputRangeError
        raise InputRangeError(*_where(args), "a field some ray of which reaches the sensor (no ray of this one "
                              "does: fully vignetted or beyond the image circle; the kernel would be empty)")
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
    from .progress import psf_progress
    from .psf.library import LibraryGrid, PSFLibrary
    lens = load_lens(args.lens)
    _check_output(args.output, "-o", suffix=".npz")
    _check_cache(args)
    grid = LibraryGrid(n_fields=args.fields, n_depths=args.depths, near_m=args.near, far_m=args.far)
    settings = _psf_settings(args)
    _check_library_memory(settings, grid)
    lib = PSFLibrary.open(lens, settings, grid, _response(args), cache=not args.no_cache)
    t = time.perf_counter()
    bar = psf_progress(f"psflib {lens.id}")
    done = lib.build(progress=bar)
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
    _check_output(args.png, "--png", suffix=".png")
    if args.library.endswith(".npz"):
        lib = PSFLibrary.load(args.library)
    else:
        lens = load_lens(args.library)
        _check_cache()
        settings = _psf_settings(args)
        _check_library_memory(settings)
        from .psf.library import LibraryGrid
        near = LibraryGrid().near_m
        if min(args.show_depths) < near:
            from .errors import InputRangeError
            raise InputRangeError("--show-depths", min(args.show_depths), f">= {near:g} m, the library's nearest "
                                  "depth bin")
        lib = PSFLibrary.open(lens, settings)
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
    """The image and depth map, checked: same size; a depth map with no valid
    pixel refused; an implausible one (another unit) or negative light warned
    about (render.inputs)."""
    import warnings

    from .io.images import read_depth, read_image
    from .render.inputs import InputWarning, depth_problems, light_problems
    img = read_image(args.image)
    depth = read_depth(args.depth, channel=args.depth_channel)
    if depth.shape != img.shape[:2]:
        from .errors import InputRangeError
        raise InputRangeError(f"depth map {args.depth}", depth.shape, f"{img.shape[:2]} (the image {args.image})")
    for msg in light_problems(img, args.image) + ([] if getattr(args, "fixed_depth", None) is not None
                                                   else depth_problems(depth, args.depth)):
        warnings.warn(msg, InputWarning)
    return img, depth


def _image_pitch(args):
    """The image's pixel pitch (mm) from --image-pixel-pitch or --pixel-pitch
    (the same thing here: PSFs are sampled at the image's pitch)."""
    from .errors import InputRangeError
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
    from .errors import InputRangeError
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


def _render_inputs(args, rgbd=None):
    """Everything simulate and bokeh check before any work: the lens, the
    output paths, the response file, the images and the geometry.
    ``rgbd``: (image, depth) already read (else from --image, --depth)."""
    from .optics.lens import load_lens
    from .render.distortion import check_interpolation
    from .render.simulate import MAX_FITTED_KERNEL, check_patch
    lens = load_lens(args.lens)
    _check_output(args.output, "-o", image=True)
    _check_output(getattr(args, "sharp_out", None), "--sharp-out", image=True)
    _check_output(getattr(args, "side_by_side", None), "--side-by-side", suffix=".png")
    _check_cache()
    check_patch(args.patch)
    check_interpolation(args.interpolation)
    if getattr(args, "noise", False):
        from .render.noise import check_noise
        if args.seed is None:
            from .errors import InputRangeError
            raise InputRangeError("--seed", None, "an integer: --noise needs an explicit seed")
        check_noise(args.full_well, args.read_noise)
    if getattr(args, "perturb", None) is not None and not 0.0 <= args.perturb_fraction <= 0.5:
        from .errors import InputRangeError
        raise InputRangeError("--perturb-fraction", args.perturb_fraction, "a number in [0, 0.5] (0.1 = +-10 %)")
    fixed = getattr(args, "fixed_depth", None)
    if fixed is not None:
        from .psf.library import LibraryGrid
        near = LibraryGrid().near_m
        if fixed < near:
            from .errors import InputRangeError
            raise InputRangeError("--fixed-depth", fixed, f">= {near:g} m, the PSF library's nearest depth bin (or inf)")
    _check_wavelength(lens, args)
    from dataclasses import replace
    settings = replace(_psf_settings(args, focus=args.command not in ("bokeh", "dof")), pixel_pitch_mm=None,
                       wavelength_nm=args.wavelength)
    response = _response(args)
    img, depth = _read_rgbd(args) if rgbd is None else rgbd
    geom, source = _geometries(args, lens, img.shape[:2])
    # the largest kernel the run may use: --kernel, or the fitted kernel's ceiling
    biggest = settings if args.kernel else replace(settings, kernel_size=MAX_FITTED_KERNEL)
    patches = -(-geom.height // args.patch) * -(-geom.width // args.patch)
    _check_library_memory(biggest, map_kernels=patches)
    return lens, settings, response, img, depth, geom, source


@contextlib.contextmanager
def _quiet_input_warnings():
    """The engine repeats the input warnings that _read_rgbd gave (naming the files): silence its copies."""
    import warnings

    from .render.inputs import InputWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        yield


def cmd_simulate(args) -> int:
    from .io.images import write_image
    from .progress import Steps, psf_progress
    from .render.simulate import LensSimulator
    lens, settings, response, img, depth, geom, source = _render_inputs(args)
    steps = Steps("dcdi simulate")
    steps.start("PSF library (built once per lens and setting, then read from the cache)")
    record = None
    if args.perturb is not None:
        from .optics.perturb import perturb_lens
        lens, record = perturb_lens(lens, seed=args.perturb, fraction=args.perturb_fraction)
    noise = {"full_well_electrons": args.full_well, "read_noise_electrons": args.read_noise} if args.noise else None
    src = _choose_psf_source(args, lens, pixel_pitch_mm=geom.pixel_pitch_mm, settings=settings,
                             focus_m=settings.focus_distance_m)
    # without --kernel, the kernel grows to hold the PSFs this depth map needs
    # (an OLF's kernels hold 99 % of the energy over its whole depth range)
    sim = LensSimulator(lens, geom, source_geometry=source, settings=settings, library=src.library,
                        response=response, patch=args.patch, distortion=not args.no_distortion,
                        interpolation=args.interpolation, fit_depth_m=None if args.kernel else depth,
                        progress=psf_progress("PSFs"), accelerator=args.accelerator)
    steps.start(f"distortion, PSF map and convolution of {img.shape[0]} x {img.shape[1]} pixels")
    with _quiet_input_warnings():
        r = sim(img, depth, fixed_depth_m=args.fixed_depth, noise=noise, seed=args.seed)
    steps.start("writing")
    write_image(args.output, r.image)
    if args.sharp_out:
        write_image(args.sharp_out, r.sharp)
    steps.done()
    print(_dump({"output": args.output, **r.info, "perturbation": record, "psf_source": src.kind,
                 "olf_file": src.olf_file if src.kind == "olf" else None}))
    return 0


def cmd_bokeh(args) -> int:
    from .io.images import write_image
    from .progress import Steps, bar, psf_progress
    from .render.multires import DEFAULT_MAX_LEVEL, check_multires
    from .render.simulate import bokeh
    check_multires(args.multires, DEFAULT_MAX_LEVEL if args.max_level is None else args.max_level, 16)
    lens, settings, response, img, depth, geom, source = _render_inputs(args)
    steps = Steps("dcdi bokeh")
    steps.start("PSF library (built once per lens, focus and setting, then read from the cache), then the blur")
    keep = tuple(args.keep) if args.keep else None
    focus_m = None if args.focus in (None, "prescribed") else args.focus
    src = _choose_psf_source(args, lens, pixel_pitch_mm=geom.pixel_pitch_mm, settings=settings, focus_m=focus_m)
    with _quiet_input_warnings():
        r = bokeh(img, depth, lens, keep=keep, focus_m=args.focus, geometry=geom, source_geometry=source,
                  distortion=args.distort, interpolation=args.interpolation, patch=args.patch,
                  occlusion=not args.plain, settings=settings, response=response, fit_kernel=not args.kernel,
                  library=src.library, progress=psf_progress("PSFs"), layer_progress=bar("depth layers", "layer"),
                  multires=args.multires, max_level=args.max_level)
    steps.start("writing")
    write_image(args.output, r.image)
    if args.side_by_side:
        from .render.pictures import side_by_side
        what = (f"keep {keep[0]:g}-{keep[1]:g} m" if keep else
                "as prescribed" if args.focus == "prescribed" else f"focus {args.focus:g} m")
        side_by_side(args.side_by_side, img if r.sharp is None else r.sharp,
                     depth if r.depth is None else r.depth, r.image, f"{lens.name}: {what}")
    steps.done()
    print(_dump({"output": args.output, **r.info, "psf_source": src.kind,
                 "olf_file": src.olf_file if src.kind == "olf" else None}))
    return 0


def _dof_networks(args, camera, h, w):
    """(estimator or None, DACN or None, its info, notes) for `dcdi dof`, all
    loaded (and refused, by name) before any work."""
    from .pipeline import shipped_lenses, shipped_model
    estimator = corrector = info = None
    if args.depth is None:
        ck = args.depth_checkpoint
        if ck is None and args.depth_backend == "dcdi":
            ck = shipped_model("depth", camera.id) if camera is not None else None
            if ck is None:
                from .models.errors import ModelError
                raise ModelError("no depth map (--depth) and no shipped depth network for "
                                 f"{'a sharp image (--camera none)' if camera is None else camera.id} (shipped: "
                                 f"{', '.join(shipped_lenses('depth')) or 'none'}); give --depth, or "
                                 "--depth-backend with --depth-checkpoint")
        from .models.depth.estimators import load_estimator
        opts = {"threads": args.threads} if args.depth_backend == "dcdi" else {}
        estimator = load_estimator(args.depth_backend, ck, **opts)
    if camera is not None:
        path = args.dacn or shipped_model("dacn", camera.id)
        if path is None:
            from .models.errors import ModelError
            raise ModelError(f"no shipped DACN for {camera.id} (shipped: {', '.join(shipped_lenses('dacn')) or 'none'});"
                             " give --dacn MODEL, or --camera none for a sharp image")
        from .models.dacn.correct import load_dacn
        corrector, info = load_dacn(path)
        trained = (info.get("da2t") or {}).get("lens")
        if trained is not None and trained != camera.id:
            from .models.errors import ModelError
            raise ModelError(f"{path} was trained for lens {trained}, not the camera {camera.id}")
    return estimator, corrector, info


def cmd_dof(args) -> int:
    from pathlib import Path

    import numpy as np
    from .io.images import read_depth, read_image, write_depth, write_image
    from .optics.lens import load_lens
    from .render.geometry import ImageGeometry
    camera = None if args.camera == "none" else load_lens(args.camera)
    img = read_image(args.image)
    depth = None
    if args.depth is not None:
        depth = read_depth(args.depth, channel=args.depth_channel)
        if depth.shape != img.shape[:2]:
            from .errors import InputRangeError
            raise InputRangeError(f"depth map {args.depth}", depth.shape, f"{img.shape[:2]} (the image {args.image})")
    lens, settings, response, _, _, geom, source = _render_inputs(
        args, rgbd=(img, depth if depth is not None else np.ones(img.shape[:2], np.float32)))
    if args.save_intermediates:
        for name in ("corrected.exr", "depth.exr"):
            _check_output(str(Path(args.save_intermediates) / name), "--save-intermediates", image=True)
    import torch
    torch.set_num_threads(args.threads)
    estimator, corrector, info = _dof_networks(args, camera, *img.shape[:2])
    from .pipeline import dof
    camera_pitch = ImageGeometry.full_sensor(camera, *img.shape[:2]).pixel_pitch_mm if camera is not None else None
    focus_m = args.focus
    with _quiet_input_warnings():
        r = dof(img, lens, keep=tuple(args.keep) if args.keep else None, focus_m=focus_m, depth_m=depth,
                estimator=estimator, corrector=corrector, corrector_info=info, camera_pitch_mm=camera_pitch,
                psf_source=args.psf_source, olf_file=args.olf, settings=settings, geometry=geom,
                source_geometry=source, response=response, distortion=args.distort, interpolation=args.interpolation,
                patch=args.patch, occlusion=not args.plain, fit_kernel=not args.kernel)
    print(f"dcdi: {r.psf_message}", file=sys.stderr)
    for note in r.notes:
        print(f"dcdi: note: {note}", file=sys.stderr)
    write_image(args.output, r.image)
    if args.save_intermediates:
        write_image(Path(args.save_intermediates) / "corrected.exr", r.corrected)
        write_depth(Path(args.save_intermediates) / "depth.exr", r.depth_m)
    if args.side_by_side:
        from .models.dacn.evaluate import panel_strip
        from .render.pictures import depth_panel
        write_image(args.side_by_side, panel_strip([img, r.corrected, depth_panel(r.depth_m), r.image]))
    times = ", ".join(f"{k} {v:.2f} s" for k, v in r.seconds.items())
    print(f"wrote {args.output}: camera {args.camera}, depth {r.depth_source}, PSFs {r.psf_source}; {times}")
    return 0


def _lens_map(items, what: str) -> dict:
    out = {}
    for item in items or []:
        lens, sep, path = item.partition("=")
        if not sep or not lens or not path:
            from .errors import InputRangeError
            raise InputRangeError(what, item, "LENS=PATH, e.g. mos-s1=out/pairs-mos-s1")
        out[lens] = path
    return out


def _report_models(args, lenses, need_dacn: bool = True):
    """{lens: {'dacn', 'depth', 'baseline'}} for the pipeline and depth reports:
    given paths, else the shipped files."""
    from .models.dacn.correct import load_dacn
    from .models.depth.export import load_depthnet
    from .models.errors import ModelError
    from .pipeline import shipped_model
    dacn, depth, base = (_lens_map(v, w) for v, w in ((args.dacn, "--dacn"), (args.depth_model, "--depth-model"),
                                                       (args.baseline, "--baseline")))
    models = {}
    for lens in lenses:
        d = dacn.get(lens) or shipped_model("dacn", lens)
        if d is None and need_dacn:
            raise ModelError(f"no DACN for {lens}: give --dacn {lens}=MODEL")
        z = depth.get(lens) or shipped_model("depth", lens)
        models[lens] = {"dacn": load_dacn(d)[0] if d else None, "depth": load_depthnet(z)[0] if z else None,
                        "baseline": load_dacn(base[lens])[0] if lens in base else None}
    return models


def cmd_report_pipeline(args) -> int:
    import torch
    from .experiments import pipeline_report as pr
    from .optics.lens import load_lens
    torch.set_num_threads(args.threads)
    pairs = _lens_map(args.pairs, "--pairs")
    models = _report_models(args, pairs)
    target = load_lens(args.target)
    keep = tuple(args.keep)
    results, times = {}, {}
    for lens, d in pairs.items():
        ids = pr.held_out(d, [], args.count)
        print(f"{lens}: {len(ids)} held-out pairs of {d}", file=sys.stderr)
        results[lens] = pr.lens_rows(lens, d, ids, models[lens], target, keep, olf_file=args.olf,
                                     pictures=Path(args.out) / "pictures",
                                     log=lambda t: print(t, file=sys.stderr))
        for size in ([] if args.quick else [(480, 640), (1280, 1920)]):
            times[f"{lens}, {size[0]} x {size[1]}"] = pr.stage_times(models[lens], target, keep, size,
                                                                   olf_file=args.olf)
    print(pr.write_report(args.out, results, times, target.id, keep), end="")
    return 0


def cmd_report_depth(args) -> int:
    import json
    import torch
    from .atomic import write_text
    from .experiments import pipeline_report as pr
    torch.set_num_threads(args.threads)
    pairs = _lens_map(args.pairs, "--pairs")
    models = _report_models(args, pairs, need_dacn=False)
    missing = [lens for lens in pairs if models[lens]["depth"] is None]
    if missing:
        from .models.errors import ModelError
        raise ModelError(f"no depth network for {', '.join(missing)}: give --depth-model LENS=MODEL")
    res = pr.depth_report(pairs, {k: v["depth"] for k, v in models.items()}, {}, args.count)
    text = pr.depth_markdown(res)
    write_text(Path(args.out) / "depth.md", text)
    write_text(Path(args.out) / "depth.json", json.dumps(res, indent=1) + "\n")
    print(text, end="")
    return 0


def cmd_report(args) -> int:
    from .experiments.psf_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_sim(args) -> int:
    from .experiments.simulation_accuracy import run_report
    return run_report(args.lens, args.out, quick=args.quick)


def cmd_report_olf(args) -> int:
    from .experiments.olf_report import run_report
    return run_report(args.olf, args.out, quick=args.quick, sweep=args.sweep, pitch_only=args.pitch_only,
                      held_out_points=args.held_out_points)


def cmd_bench(args) -> int:
    from .experiments import bench
    return bench.run(args.what, args)


def cmd_demo(args) -> int:
    from . import demo
    return demo.run(args.out)


# ------------------------------------------------------- olf (dcdi_core.models)
def _progress_bar(desc: str, every: int = 0):
    """(progress(step, total, loss), log(text), close()) for a training run:
    a tqdm bar on a terminal, made at the first step so that its rate is the
    training's (a resumed run starts at its step); off a terminal (a
    background run's log) one line every ``every`` steps and at the end, and
    the run's own messages."""
    tty = sys.stderr.isatty()
    bar = None
    t_start = time.perf_counter()

    def progress(step, total, loss):
        nonlocal bar
        if not tty:
            if every and (step % every == 0 or step == total):
                print(f"{desc}: iteration {step}/{total}, loss {loss:.3g}, "
                      f"{time.perf_counter() - t_start:.0f} s since start", file=sys.stderr, flush=True)
            return
        if bar is None:
            try:
                from tqdm import tqdm
            except ImportError:     # no bar without tqdm (requirements.txt has it)
                return
            bar = tqdm(total=total, initial=step - 1, desc=desc, unit="it", file=sys.stderr, dynamic_ncols=True)
        bar.set_postfix(loss=f"{loss:.3g}", refresh=False)
        bar.update(step - bar.n)

    def log(text):
        if bar is not None:
            bar.write(text)
        else:
            print(f"{text} ({time.perf_counter() - t_start:.0f} s since start)", file=sys.stderr, flush=True)

    def close():
        if bar is not None:
            bar.close()
    return progress, log, close


def _add_device_option(parser, torchrun: bool = True) -> None:
    """--device of a torch command (not a setting: a run resumes on another device)."""
    parser.add_argument("--device", default="auto", metavar="auto|cpu|cuda[:N]",
                        help="where torch computes: auto (CUDA when torch sees a device, else the CPU), cpu, "
                             "cuda or cuda:N" + ("; under torchrun each process takes cuda:LOCAL_RANK"
                                                 if torchrun else ""))


def _torchrun_worker() -> bool:
    """A torchrun process other than rank 0 (it trains but writes nothing)."""
    import os
    return os.environ.get("RANK", "0") not in ("", "0")


def _ran_on(where: dict) -> str:
    n = where.get("world_size", 1)
    return f"ran on {where.get('device', 'cpu')}" + (f", {n} processes (torchrun)" if n > 1 else "")


def _run_training(desc: str, run, train_fn, every: int = 0):
    """train_fn(progress=..., log=...) under a progress bar; None (after
    saying how to resume) when interrupted."""
    progress, log, close = _progress_bar(desc, every)
    try:
        result = train_fn(progress=progress, log=log)
    except KeyboardInterrupt:
        close()
        print(f"dcdi: interrupted; the last checkpoint is in {run}: run the same command to resume",
              file=sys.stderr)
        return None
    close()
    return result


def cmd_olf_train(args) -> int:
    import os
    from pathlib import Path
    from .models.olf.data import PSFDataConfig
    from .models.olf.config import OLFTrainConfig
    data = PSFDataConfig(lenses=tuple(args.lens), variant=args.variant, pupil_samples=args.rays,
                         n_wavelengths=args.wavelengths, n_fields=args.fields, n_depths=args.depths,
                         focus_lenses=tuple(args.focus_lens or ()), focus_range_m=tuple(args.focus_range),
                         focus_bins=args.focus_bins,
                         offgrid=args.offgrid, held_out=args.held_out, seed=args.seed)
    config = OLFTrainConfig(data=data, size=args.size, iters=args.iters, batch=args.batch, lr=args.lr,
                            seed=args.seed, threads=args.threads or (os.cpu_count() or 1),
                            checkpoint_every=args.checkpoint_every)
    from .models.olf.export import export_olf               # torch from here on
    from .models.olf.train import train
    run = Path(args.run or (str(args.output) + ".run"))
    result = _run_training("olf train", run, lambda **kw: train(config, run, device=args.device, **kw),
                           config.checkpoint_every)
    if result is None:
        return 130
    if _torchrun_worker():
        return 0                                        # rank 0 exports and reports
    meta = export_olf(result, args.output, weights=args.weights, dtype=args.dtype)
    h = meta["held_out"]["mean"]
    rate = result.step / result.seconds if result.seconds > 0 else float("nan")
    print(f"wrote {args.output} ({meta['parameters']} parameters, {os.path.getsize(args.output)} bytes; "
          f"run folder {run})")
    print(f"held-out ({args.weights}): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM "
          + (f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a")
          + f", relative L1 {h['rel_l1']:.4f}; {result.seconds:.1f} s of training ({rate:.1f} it/s; PSF data not included)")
    print(_ran_on(result.where))
    return 0


def cmd_olf_points(args) -> int:
    from .models.olf.data import PSFDataConfig, build_data
    data = PSFDataConfig(lenses=tuple(args.lens), pupil_samples=args.rays, n_wavelengths=args.wavelengths,
                         n_fields=args.fields, n_depths=args.depths, focus_lenses=tuple(args.focus_lens or ()),
                         focus_range_m=tuple(args.focus_range), focus_bins=args.focus_bins, offgrid=args.offgrid,
                         held_out=args.held_out, seed=args.seed)
    t0 = time.perf_counter()
    d = build_data(data, points_file=args.output, log=lambda t: print(t, file=sys.stderr))
    print(f"wrote {args.output}: " + ", ".join(f"{ls.lens.id} {len(ls.val_x)} held-out" for ls in d.lenses)
          + f" ({time.perf_counter() - t0:.0f} s)")
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
        bands = (((info["held_out"] or {}).get("focus") or {}).get(e["id"]) or {})
        for band, hb in sorted(bands.items(), key=lambda b: ("prescribed", "far", "mid", "near").index(b[0])):
            print(f"  {'':<14}   held-out at {band} focus ({hb['n']} points): {hb['psnr_8bit']:.2f} dB, SSIM "
                  + (f"{hb['ssim_8bit']:.4f}" if hb.get("ssim_8bit") is not None else "n/a")
                  + f", rel. L1 {hb['rel_l1']:.4f}")
    h = (info["held_out"] or {}).get("mean")
    if h:
        ssim = f"{h['ssim_8bit']:.4f}" if h["ssim_8bit"] is not None else "n/a"
        print(f"  held-out (mean over lenses): PSNR {h['psnr_8bit']:.2f} dB (8-bit, peak scale), SSIM {ssim}, "
              f"relative L1 {h['rel_l1']:.4f}, PSNR {h['psnr_sum']:.2f} dB (sum-normalised)")
    t = info["training"] or {}
    if t:
        print(f"  trained {t.get('iterations')} iterations in {t.get('seconds', 0):.0f} s; checksum "
              f"{info['checksum'][:16]}...")


def _add_olf_data_options(t) -> None:
    """The options of `olf train` and `olf points` that decide the traced samples."""
    t.add_argument("--offgrid", type=int, default=256, help="traced off-grid training points per lens")
    t.add_argument("--held-out", type=_positive_int, default=64, help="traced held-out points per lens")
    t.add_argument("--rays", type=_positive_int, default=64, help="pupil samples per side (PSF settings)")
    t.add_argument("--wavelengths", type=_positive_int, default=31, help="wavelengths per PSF")
    t.add_argument("--fields", type=_positive_int, default=64, help="library fields")
    t.add_argument("--depths", type=_positive_int, default=20, help="library depth bins (plus infinity)")
    t.add_argument("--focus-lens", action="append", help="radial: learn this lens across focus distances")
    t.add_argument("--focus-range", type=float, nargs=2, default=(0.7, math.inf), metavar=("NEAR", "FAR"),
                   help="focus distances learned (m, FAR may be inf; default 0.7 inf); the prescribed focus "
                        "is learned besides")
    t.add_argument("--focus-bins", type=_positive_int, default=3,
                   help="PSF libraries per focus lens, uniform in diopters over the focus range (default 3; "
                        "each is one library build), plus the prescribed one")
    t.add_argument("--seed", type=int, default=0, help="seed of weights, sampling and traced points")


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
    t.add_argument("--threads", type=_positive_int, default=None, help="torch threads (default: all cores)")
    _add_device_option(t)
    t.add_argument("-o", "--output", required=True, help="the exported OLF (.npz)")
    t.add_argument("--run", default=None, help="run folder for checkpoints (default OUTPUT.run)")
    t.add_argument("--checkpoint-every", type=_positive_int, default=500, help="iterations between checkpoints")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights to export")
    t.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="how the exported weights are stored (float16 halves the file; the runtime computes in "
                        "float32 and the held-out figures printed are the stored file's)")
    _add_olf_data_options(t)
    t.set_defaults(func=cmd_olf_train)
    pt = osub.add_parser("points", help="the traced off-grid and held-out points of a training config (no training)",
                         description="Trace (or read from the PSF cache) what `olf train` with the same data "
                                     "options would train and validate on, into a points file: e.g. the held-out "
                                     "points of an older OLF, for `dcdi report olf --held-out-points`.")
    pt.add_argument("--lens", action="append", required=True, help="lens id (repeat; the order decides the seeds)")
    pt.add_argument("-o", "--output", required=True, help="the points file (.npz)")
    _add_olf_data_options(pt)
    pt.set_defaults(func=cmd_olf_points)
    i = osub.add_parser("info", help="what an exported OLF holds: lenses, sizes, held-out figures")
    i.add_argument("file", nargs="*", help="exported OLF files (.npz); default: the shipped ones")
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=cmd_olf_info)


# ------------------------------------------------------ dacn (dcdi_core.models)
def _shard(text: str):
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}': expected I/N, e.g. 0/4") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"'{text}': need 0 <= I < N")
    return i, n


def cmd_dacn_pairs(args) -> int:
    from .models.dacn.data import DA2TConfig, build_pairs
    from .dataset.rgbd import open_source
    source = open_source(args.source, args.kind)
    noise = None if args.no_noise else {"full_well_electrons": args.full_well, "read_noise_electrons": args.read_noise}
    config = DA2TConfig(lens=args.lens, perturb_fraction=args.perturb, noise=noise,
                        baseline_depth_m=args.baseline_depth, sensor_px=args.sensor_px, pupil_samples=args.rays,
                        n_wavelengths=args.wavelengths, n_fields=args.fields, n_depths=args.depths,
                        lens_pool=args.lens_pool, saturate=not args.no_saturate, seed=args.seed)
    t0 = time.perf_counter()
    done = build_pairs(source, args.output, config, variants=args.variants, shard=args.shard,
                       log=lambda t: print(t, file=sys.stderr))
    print(f"{len(done)} DA2T pairs of {source.name} ({len(source)} frames) for {args.lens} in {args.output} "
          f"({time.perf_counter() - t0:.1f} s this run)")
    return 0


def cmd_train_dacn(args) -> int:
    from pathlib import Path
    from .models.dacn.config import DACNTrainConfig
    arch = {}
    if args.no_rdicab:
        arch["rdicab"] = False
    if args.no_d2cb:
        arch["d2cb"] = False
    for k in ("racm", "depth_encoding", "channels", "groups", "blocks"):
        if getattr(args, k) is not None:
            arch[k] = getattr(args, k)
    config = DACNTrainConfig(data=args.data, config=args.config, arch=arch, input=args.input, iters=args.iters,
                             batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed, threads=args.threads,
                             checkpoint_every=args.checkpoint_every, validate_every=args.validate_every,
                             train_scenes=args.train_scenes)
    from .models.dacn.train import train_dacn       # torch from here on
    run = Path(args.output)
    result = _run_training("dacn train", run, lambda **kw: train_dacn(config, run, device=args.device, **kw),
                           config.checkpoint_every)
    if result is None:
        return 130
    if _torchrun_worker():
        return 0                                        # rank 0 reports
    v = result.validation["ema"].get("mean")
    rate = result.step / result.seconds if result.seconds > 0 else float("nan")
    print(f"trained {run} ({args.config}, {result.step} iterations, {result.seconds:.1f} s here, {rate:.2f} it/s)")
    if v:
        print(f"validation ({len(result.data.val)} pairs, EMA): PSNR {v['psnr']:.2f} dB (input {v['psnr_input']:.2f})"
              + (f", SSIM {v['ssim']:.4f} (input {v['ssim_input']:.4f})" if "ssim" in v else ""))
    else:
        print("no validation pairs (the split gave no 'val' scene)")
    print(_ran_on(result.where))
    return 0


def cmd_correct(args) -> int:
    from .io.images import check_image_output, read_image, write_image
    if args.depth is None:
        print("dcdi: error: correction needs the scene's depth: give --depth DEPTH (metres: EXR 'Z', .npy, or a "
              "16-bit PNG in mm), e.g. the factory's depth/<id>.exr or a metric monocular estimate of the capture",
              file=sys.stderr)
        return 2
    out = check_image_output(args.output)
    from .models.common.distributed import resolve_device
    resolve_device(args.device)                         # refused before any image is read
    from .dataset.rgbd import read_any_depth
    image = read_image(args.image)
    depth = read_any_depth(args.depth)
    import torch
    torch.set_num_threads(args.threads)
    from .models.dacn.correct import correct, load_dacn
    model, info = load_dacn(args.model, weights=args.weights, device=args.device)
    trained = (info.get("da2t") or {}).get("lens")
    if args.lens is not None and trained is not None and args.lens != trained:
        print(f"dcdi: error: {args.model} was trained for lens {trained}, not {args.lens}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    tty = sys.stderr.isatty()

    def progress(done, total):
        if tty:
            print(f"\rdcdi correct: tile {done}/{total}", end="" if done < total else "\n", file=sys.stderr)
    result = correct(model, image, depth, tile=args.tile, overlap=args.overlap, progress=progress)
    write_image(out, result)
    print(f"wrote {out} ({image.shape[1]} x {image.shape[0]}, {time.perf_counter() - t0:.1f} s, "
          f"lens {trained or 'unknown'}, on {info['device']})")
    return 0


def cmd_train_depth(args) -> int:
    from pathlib import Path
    from .models.depth.config import DepthTrainConfig
    config = DepthTrainConfig(data=args.data, widths=tuple(args.widths), input=args.input, iters=args.iters,
                              batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed, threads=args.threads,
                              checkpoint_every=args.checkpoint_every)
    from .models.depth.train import train_depth
    run = Path(args.output)
    result = _run_training("depth train", run, lambda **kw: train_depth(config, run, **kw), config.checkpoint_every)
    if result is None:
        return 130
    v = result.validation
    print(f"trained {run} ({result.step} iterations, {result.seconds:.1f} s here)"
          + (f"; validation (EMA, from the {args.input}): AbsRel {v['abs_rel']:.3f}, RMSE {v['rmse']:.2f} m, "
             f"delta1 {v['delta1']:.3f}" if v else ""))
    return 0


def _exported(args, meta: dict) -> int:
    """The line both export commands print about the file they wrote."""
    print(f"wrote {args.output} ({Path(args.output).stat().st_size / 1e6:.2f} MB, {args.dtype}, {meta['weights']} "
          f"weights, lens {meta['lens']}, {meta['step']} iterations)")
    return 0


def cmd_depth_export(args) -> int:
    from .models.depth.export import export_depthnet
    return _exported(args, export_depthnet(args.run, args.output, weights=args.weights, dtype=args.dtype))


def _model_splits(runs: dict) -> list:
    """The recorded splits of the runs among ``runs`` {name: path} (run
    folders and checkpoints beside one; an exported file names its run's)."""
    from pathlib import Path
    from .models.common.split import Split
    out = []
    for path in runs.values():
        p = Path(path)
        folder = p if p.is_dir() else p.parent
        if (folder / "split.json").exists():
            out.append(Split.load(folder / "split.json"))
    return out


def cmd_eval(args) -> int:
    import json
    from pathlib import Path
    runs = {args.name: args.run}
    for item in args.compare:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            print(f"dcdi: error: --compare {item!r}: expected NAME=RUN", file=sys.stderr)
            return 2
        if name in runs or name == "capture":
            print(f"dcdi: error: --compare {item!r}: the name {name!r} is taken", file=sys.stderr)
            return 2
        runs[name] = path
    for name, path in runs.items():
        if not Path(path).exists():
            print(f"dcdi: error: model {name}: {path} does not exist", file=sys.stderr)
            return 2
    import torch
    torch.set_num_threads(args.threads)
    from .models.dacn.correct import load_dacn
    from .models.dacn.evaluate import evaluate_models, held_out_pairs, markdown_tables, write_pictures
    ids, _ = held_out_pairs(args.data, _model_splits(runs))
    models = {name: load_dacn(path, weights=args.weights)[0] for name, path in runs.items()}
    tty = sys.stderr.isatty()

    def progress(done, total):
        if tty:
            print(f"\rdcdi eval: pair {done}/{total}", end="" if done < total else "\n", file=sys.stderr)
    lp = None
    if args.lpips:
        from .models.common.lpips import load_lpips
        lp = load_lpips(*args.lpips)
    ev, kept = evaluate_models(models, args.data, ids=ids, tile=args.tile, overlap=args.overlap,
                               progress=progress, keep_outputs=args.pictures_count if args.pictures else 0, lpips=lp)
    print(f"{len(ids)} held-out pairs of {args.data}; PSNR dB / SSIM over the imaged pixels")
    print(markdown_tables(ev), end="")
    for name, sec in ev.seconds.items():
        print(f"{name}: {sec / len(ids):.2f} s per pair")
    if args.json:
        from .atomic import write_text
        write_text(args.json, json.dumps(dict(ev.as_dict(), runs=runs), indent=1) + "\n")
    if args.pictures:
        paths = write_pictures(kept, args.pictures, list(models))
        print(f"wrote {len(paths)} pictures to {args.pictures} (capture | {' | '.join(models)} | target)")
    return 0


def cmd_dacn_export(args) -> int:
    from .models.dacn.export import export_dacn
    return _exported(args, export_dacn(args.run, args.output, weights=args.weights, dtype=args.dtype))


def add_dacn_commands(sub) -> None:
    """`dcdi dacn pairs`, `dcdi train dacn`, `dcdi correct`: the depth-aware correction network."""
    q = sub.add_parser("dacn", help="depth-aware correction network: DA2T training pairs",
                       description="DACN's training data. " + UNITS)
    dsub = q.add_subparsers(dest="dacn_command", required=True, metavar="SUBCOMMAND")
    t = dsub.add_parser("pairs", help="pre-build DA2T pairs from an RGB-D source (resumable, sharded)",
                        description="Simulate every frame of an RGB-D source through a (perturbed) lens: "
                                    "capture, aligned target, depth on the sensor, depth-unaware baseline.")
    t.add_argument("source", help="factory folder, images/+depth/ folder, NYUv2 labeled .mat or Middlebury 2014")
    t.add_argument("--kind", choices=["factory", "folder", "nyuv2", "middlebury2014"], default=None,
                   help="the source's kind (default: found from what is there)")
    t.add_argument("--lens", required=True, help="lens id")
    t.add_argument("-o", "--output", required=True, help="pairs folder")
    t.add_argument("--variants", type=_positive_int, default=1, help="perturbed lenses per frame (default 1)")
    t.add_argument("--perturb", type=float, default=0.10, help="perturbation fraction (default 0.10 = +-10 %%)")
    t.add_argument("--lens-pool", type=int, default=0,
                   help="K perturbed lenses shared by all frames (0: a new one per frame; each costs a PSF library)")
    t.add_argument("--baseline-depth", type=float, default=2.0, help="the depth-unaware baseline's depth, m")
    t.add_argument("--no-noise", action="store_true", help="no sensor noise")
    t.add_argument("--no-saturate", action="store_true",
                   help="keep values above 1 (default: capture, baseline and target clipped to [0, 1] as a sensor "
                        "records them)")
    t.add_argument("--full-well", type=float, default=10000.0, help="full well, electrons")
    t.add_argument("--read-noise", type=float, default=3.0, help="read noise, electrons RMS")
    t.add_argument("--sensor-px", type=int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                   help="frames are the centre of a sensor of this many pixels (the paper: 1280 1920)")
    t.add_argument("--rays", type=_positive_int, default=64, help="pupil samples per side (PSF settings)")
    t.add_argument("--wavelengths", type=_positive_int, default=31, help="wavelengths per PSF")
    t.add_argument("--fields", type=_positive_int, default=64, help="library fields")
    t.add_argument("--depths", type=_positive_int, default=20, help="library depth bins (plus infinity)")
    t.add_argument("--seed", type=int, default=0, help="seed of perturbations and noise")
    t.add_argument("--shard", type=_shard, default=(0, 1), help="I/N: the frames at positions i %% N == I")
    t.set_defaults(func=cmd_dacn_pairs)

    q = sub.add_parser("train", help="train a network (dacn, depth)")
    tsub = q.add_subparsers(dest="train_command", required=True, metavar="NETWORK")
    t = tsub.add_parser("dacn", help="train (or resume) DACN on pre-built DA2T pairs",
                        description="Train DACN (CPU, seeded, Adam, L1, EMA). Checkpoints go to the run folder; "
                                    "the same command again resumes a killed run and ends where an uninterrupted "
                                    "one would.")
    t.add_argument("--data", required=True, help="pairs folder (dcdi dacn pairs)")
    t.add_argument("--config", default="tiny", help="named configuration: tiny, tiny-rb, demo, paper")
    t.add_argument("--iters", type=_positive_int, default=1000, help="iterations (the paper: 200000)")
    t.add_argument("-o", "--output", required=True, help="run folder")
    t.add_argument("--batch", type=_positive_int, default=4, help="batch (default 4; the paper 8)")
    t.add_argument("--crop", type=_positive_int, default=128, help="crop size (default 128; the paper 256)")
    t.add_argument("--lr", type=float, default=2e-4, help="initial learning rate (halved at 50/80/90/95 %%)")
    t.add_argument("--seed", type=int, default=0, help="seed of weights and crops")
    t.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    _add_device_option(t, torchrun=True)
    t.add_argument("--checkpoint-every", type=_positive_int, default=500, help="iterations between checkpoints")
    t.add_argument("--validate-every", type=int, default=0, help="iterations between validations (0: at the end)")
    t.add_argument("--input", choices=["capture", "baseline"], default="capture",
                   help="train on the depth-aware capture (DA2T) or the depth-unaware baseline")
    t.add_argument("--no-rdicab", action="store_true", help="ablation: without RDICAB")
    t.add_argument("--no-d2cb", action="store_true", help="ablation: without D2CB")
    t.add_argument("--racm", choices=["rb", "rstb"], default=None, help="replace the blocks (EDSR or Swin)")
    t.add_argument("--depth-encoding", choices=["minmax", "diopter"], default=None, help="depth at the input")
    t.add_argument("--channels", type=_positive_int, default=None, help="override C")
    t.add_argument("--groups", type=_positive_int, default=None, help="override G")
    t.add_argument("--blocks", type=_positive_int, default=None, help="override B")
    t.add_argument("--train-scenes", type=int, default=0,
                   help="train on this many of the training scenes (0: all; for a data-size curve)")
    t.set_defaults(func=cmd_train_dacn)

    t = tsub.add_parser("depth", help="train (or resume) the small depth network on DA2T pairs",
                        description="Train the depth network (capture -> metric depth) on pre-built DA2T pairs: "
                                    "seeded, atomic checkpoints, exact resume, the split by scene of the pairs.")
    t.add_argument("--data", required=True, help="pairs folder (dcdi dacn pairs)")
    t.add_argument("--iters", type=_positive_int, default=2000, help="iterations")
    t.add_argument("-o", "--output", required=True, help="run folder")
    t.add_argument("--widths", type=_positive_int, nargs="+", default=[12, 24, 48, 64], help="U-Net level widths")
    t.add_argument("--input", choices=["capture", "target"], default="capture",
                   help="learn from the aberrated capture (default) or the sharp image")
    t.add_argument("--batch", type=_positive_int, default=4, help="batch (default 4)")
    t.add_argument("--crop", type=_positive_int, default=128, help="crop size (default 128)")
    t.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (cosine to 1 %%)")
    t.add_argument("--seed", type=int, default=0, help="seed of weights and crops")
    t.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    t.add_argument("--checkpoint-every", type=_positive_int, default=500, help="iterations between checkpoints")
    t.set_defaults(func=cmd_train_depth)

    q = sub.add_parser("depth", help="the depth network's files", description="The depth network's files.")
    qsub = q.add_subparsers(dest="depth_command", required=True, metavar="SUBCOMMAND")
    t = qsub.add_parser("export", help="write a depth run as a shipped .npz (no pickle)")
    t.add_argument("run", help="run folder or checkpoint.pt")
    t.add_argument("-o", "--output", required=True, help="the .npz to write")
    t.add_argument("--dtype", choices=["float16", "float32"], default="float16", help="storage dtype")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights")
    t.set_defaults(func=cmd_depth_export)

    t = sub.add_parser("eval", help="score trained DACNs on held-out pairs, per scene and depth band",
                       description="PSNR / SSIM (over the imaged pixels) of each model's correction of the "
                                   "depth-aware captures, beside the uncorrected capture: mean, per depth band "
                                   "and per scene. Pairs of scenes a model trained or validated on are skipped.")
    t.add_argument("run", help="a DACN run folder, checkpoint.pt or exported .npz")
    t.add_argument("--data", required=True, help="pairs folder with the test pairs (dcdi dacn pairs)")
    t.add_argument("--compare", action="append", default=[], metavar="NAME=RUN",
                   help="another model to score beside it, e.g. depth-unaware=out/baseline (repeatable)")
    t.add_argument("--name", default="dacn", help="the first model's name in the tables (default dacn)")
    t.add_argument("--pictures", default=None, metavar="DIR",
                   help="write capture | corrections | target PNGs of the first pairs here")
    t.add_argument("--pictures-count", type=_positive_int, default=3, help="pairs to picture (default 3)")
    t.add_argument("--json", default=None, metavar="FILE", help="write all scores as JSON")
    t.add_argument("--weights", choices=["ema", "model"], default="ema",
                   help="the runs' EMA or raw weights (an exported file has one kind)")
    t.add_argument("--lpips", nargs=2, default=None, metavar=("ALEXNET.pth", "LIN.pth"),
                   help="also LPIPS (AlexNet, v0.1) from weights on this disk: torchvision's alexnet-owt-*.pth and "
                        "the lpips package's weights/v0.1/alex.pth (never downloaded)")
    t.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    t.add_argument("--tile", type=_positive_int, default=256, help="tile size, px (default 256)")
    t.add_argument("--overlap", type=int, default=32, help="tile overlap, px (default 32)")
    t.set_defaults(func=cmd_eval)

    t = dsub.add_parser("export", help="write a trained run's DACN as a shipped .npz (no pickle)",
                        description="Export the EMA weights of a DACN run to .npz (float16 by default) with "
                                    "its spec, training config and DA2T settings; `dcdi correct --model` reads it.")
    t.add_argument("run", help="run folder or checkpoint.pt")
    t.add_argument("-o", "--output", required=True, help="the .npz to write")
    t.add_argument("--dtype", choices=["float16", "float32"], default="float16", help="storage dtype")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights")
    t.set_defaults(func=cmd_dacn_export)

    t = sub.add_parser("correct", help="undo a lens's blur with a trained DACN (tiled, any size)",
                       description="Correct a capture with a trained DACN: overlapping tiles cross-faded, "
                                   "memory bounded by one tile. " + UNITS)
    t.add_argument("--image", required=True, help="the capture (EXR linear, or PNG/JPEG sRGB)")
    t.add_argument("--depth", default=None, help="its depth map in metres (EXR, .npy, 16-bit PNG in mm)")
    t.add_argument("--model", required=True, help="a DACN run folder, its checkpoint.pt or an exported .npz")
    t.add_argument("--lens", default=None, help="refuse a model trained for another lens")
    t.add_argument("-o", "--output", required=True, help="the corrected image (.exr, .png, .jpg)")
    t.add_argument("--tile", type=_positive_int, default=256, help="tile size, px (default 256)")
    t.add_argument("--overlap", type=int, default=32, help="tile overlap, px (default 32)")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights")
    t.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    _add_device_option(t, torchrun=False)
    t.set_defaults(func=cmd_correct)


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
    s_.add_argument("library", help="a library file (.npz from psflib build: its own settings and bins) or a "
                                    "lens id or .toml path (its library with the options below, from the cache)")
    s_.add_argument("--png", required=True, metavar="FILE.png", help="the picture to write (PNG)")
    s_.add_argument("--show-fields", type=float, nargs="+", default=[0.0, 0.5, 0.7, 1.0], metavar="F",
                    help="fields to show, normalised image height in [0, 1] (default 0 0.5 0.7 1); from a "
                         "file, the nearest fields it holds")
    s_.add_argument("--show-depths", type=_depth, nargs="+", default=[0.7, 1.0, 2.0, 5.0, math.inf], metavar="D",
                    help="depths to show, metres >= 0.7 or inf (default 0.7 1 2 5 inf); from a file, the "
                         "nearest computed bins")
    psf_options(s_)
    s_.set_defaults(func=cmd_psflib_show)

    from .render.distortion import INTERPOLATIONS
    from .render.simulate import DEFAULT_INTERPOLATION

    def rgbd_options(q, depth_required=True, image_help="all-in-focus image (EXR linear, or PNG/JPEG sRGB)"):
        q.add_argument("--image", required=True, help=image_help)
        q.add_argument("--depth", required=depth_required,
                       help="metric depth map (EXR, metres from the lens; NaN/0/<0 invalid)"
                            + ("" if depth_required else "; without it, it is estimated from the image"))
        q.add_argument("--depth-channel", default=None, metavar="NAME",
                       help="the depth map's channel, e.g. Z or ViewLayer.Depth.Z (default: the first of "
                            "Z, depth.Z, Depth.V, V, depth, R, Y found)")
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
        psf_options(q, focus=q.prog.split()[-1] not in ("bokeh", "dof"), render=True)
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
    q.add_argument("--accelerator", choices=("torch",), default=None,
                   help="run the PSF map and convolution in torch (the same result to float32 rounding; "
                        "default numpy, as in Blender)")
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
    q.add_argument("--multires", type=float, default=None, metavar="C",
                   help="multi-resolution blur: a patch whose kernel holds half its energy within a radius "
                        ">= C 2^s px is blurred at 1/2^s of the resolution (error and time against the exact path: "
                        "`dcdi report simulation-accuracy`); default: every layer at full resolution")
    q.add_argument("--max-level", type=int, default=None, metavar="S",
                   help="with --multires: at most 1/2^S of the resolution (default 2)")
    q.add_argument("--side-by-side", default=None, metavar="PNG", help="also write input | depth | result")
    q.set_defaults(func=cmd_bokeh)

    q = sub.add_parser("dof", help="DCDI end to end: a minimalist-lens capture -> another lens's depth of field",
                       description="Depth (given, or estimated from the capture), correction of the camera lens's "
                                   "aberrations (DACN), then the target lens's occlusion-aware bokeh with PSFs from "
                                   "the Omni-Lens-Field where it covers the request, else traced. " + UNITS)
    rgbd_options(q, depth_required=False, image_help="the capture (EXR linear, or PNG/JPEG sRGB)")
    q.add_argument("--camera", required=True,
                   help="the lens that took the capture (its shipped DACN corrects it), or 'none' for a sharp image")
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--keep", type=float, nargs=2, metavar=("NEAR", "FAR"), help="depth range kept sharp, metres")
    g.add_argument("--focus", type=_focus, metavar="D", help="focus the target lens at D metres, or 'prescribed'")
    q.add_argument("--dacn", default=None, metavar="MODEL",
                   help="the correction network (default: the shipped one of --camera)")
    q.add_argument("--depth-backend", default="dcdi", choices=["dcdi", "unidepth", "depth-anything-v2", "depth-pro"],
                   help="the estimator when no --depth is given (default dcdi: the shipped depth network of "
                        "--camera)")
    q.add_argument("--depth-checkpoint", default=None, metavar="PATH",
                   help="the estimator's checkpoint on this disk (never downloaded)")
    q.add_argument("--save-intermediates", default=None, metavar="DIR",
                   help="also write corrected.exr and depth.exr there")
    q.add_argument("--side-by-side", default=None, metavar="PNG", help="also write capture | corrected | depth | result")
    q.add_argument("--distort", action="store_true", help="also apply the target lens's distortion")
    q.add_argument("--plain", action="store_true", help="plain patch-wise blur instead of occlusion-aware layers")
    q.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    q.set_defaults(func=cmd_dof)

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
    r.add_argument("--pitch-only", action="store_true",
                   help="only the kernels at coarser pixel pitches (area-resampled) against kernels traced there")
    r.add_argument("--held-out-points", default=None, metavar="RUN/points.npz",
                   help="only: every file scored on one training run's held-out points, per lens and focus "
                        "(compares an old and a new OLF on the same traced points)")
    r.set_defaults(func=cmd_report_olf)

    for name, helptext in (("pipeline", "DCDI end to end on held-out factory pairs against the ideal; stage times"),
                           ("depth", "the depth network on held-out factory pairs: AbsRel, RMSE, delta1")):
        r = rsub.add_parser(name, help=helptext)
        r.add_argument("--pairs", action="append", required=True, metavar="LENS=DIR",
                       help="a camera lens's DA2T pairs (their test split is used), e.g. mos-s1=out/pairs-mos-s1")
        r.add_argument("--dacn", action="append", default=None, metavar="LENS=MODEL",
                       help="a lens's DACN (default: the shipped one)")
        r.add_argument("--depth-model", action="append", default=None, metavar="LENS=MODEL",
                       help="a lens's depth network (default: the shipped one)")
        r.add_argument("--baseline", action="append", default=None, metavar="LENS=MODEL",
                       help="a lens's depth-unaware DACN (a row of its own)")
        r.add_argument("--count", type=_positive_int, default=8, help="held-out pairs per lens (default 8)")
        r.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
        r.add_argument("--out", default="out/report", help="folder for the table (Markdown), JSON and pictures")
        if name == "pipeline":
            r.add_argument("--target", default="6p", help="the target lens (default 6p)")
            r.add_argument("--keep", type=float, nargs=2, default=[0.7, 1.5], metavar=("NEAR", "FAR"),
                           help="depth range kept sharp, metres (default 0.7 1.5)")
            r.add_argument("--olf", default=None, metavar="FILE.npz", help="the OLF (default: the shipped one)")
            r.add_argument("--quick", action="store_true", help="no stage timing at full sizes (for tests)")
            r.set_defaults(func=cmd_report_pipeline)
        else:
            r.set_defaults(func=cmd_report_depth)

    q = sub.add_parser("bench", help="benchmarks (times, not tests)",
                       description="Benchmarks of the engine; the dataset factory's is `python build.py bench "
                                   "factory` (it starts the Blender layer, which the engine never does).")
    q.add_argument("what", choices=["trace", "psflib", "render", "dacn"], help="what to benchmark")
    q.add_argument("--rays", type=_positive_int, default=1 << 20, help="rays per trace (default 2^20)")
    q.add_argument("--repeat", type=_positive_int, default=3, help="timed repetitions (best is kept)")
    q.add_argument("--quick", action="store_true", help="psflib: a small library (for tests)")
    q.add_argument("--threads", type=_positive_int, default=1, help="dacn: torch threads (default 1)")
    q.set_defaults(func=cmd_bench)

    q = sub.add_parser("demo", help="the demo job: lens reports, spot diagrams and PSFs of all lenses, simulation "
                                    "and bokeh on a synthetic scene (python build.py demo adds a factory sample)")
    q.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    q.set_defaults(func=cmd_demo)

    add_olf_commands(sub)
    add_dacn_commands(sub)
    return p


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"dcdi: warning: {_one_line(message)}", file=sys.stderr)


OUT_OF_MEMORY = ("out of memory: the work did not fit in this machine's memory; lower --rays (memory grows as its "
                 "square), --wavelengths or --kernel, or use a smaller image")


def main(argv=None) -> int:
    """The `dcdi` command: exit 0 on success, 2 with one line on stderr for any
    error a user can cause (a DcdiError, or memory running out); anything
    else is a bug and keeps its traceback."""
    import warnings

    from .errors import DcdiError
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning          # one line each, no source line
        try:
            return args.func(args)
        except DcdiError as e:
            print(f"dcdi: error: {_one_line(e)}", file=sys.stderr)
            return 2
        except MemoryError:
            print(f"dcdi: error: {OUT_OF_MEMORY}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("dcdi: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
