"""`dcdi psf` and `dcdi psflib build|show`: PSFs of a lens, one or a library,
traced or served by the Omni-Lens-Field.

Engine imports are inside the handlers so that `dcdi --help` stays fast.
"""
from __future__ import annotations

import math
import time

from .common import (UNITS, add_aperture_options, add_psf_options, add_psf_source_options, add_subcommands, check_cache,
                     check_olf_file, check_output, check_wavelength, depth_value, positive_int,
                     load_lens_with_aperture, print_table_or_json, psf_settings, response, say)
from .lens import add_field_options, no_ray_error


def choose_psf_source(args, lens, *, pixel_pitch_mm, settings, focus_m, extra_reason=None):
    """The PSF source of a psf / simulate / bokeh request (``--psf-source``,
    ``--olf``, ``--basis``): the source rule (``psf.rule``); says which
    and why on standard error (one line).
    ``extra_reason``: why neither can serve this request whatever they hold
    (then traced)."""
    from ..errors import ModelError
    from ..psf.sources import PSFSource, psf_source
    if extra_reason is not None and args.psf_source != "trace":
        if args.psf_source in ("olf", "basis", "raymap"):
            raise ModelError(f"--psf-source {args.psf_source}: it cannot serve this request: {extra_reason}")
        src = PSFSource("trace", f"PSFs traced: {extra_reason}", lens=lens)
    else:
        src = psf_source(lens, source=args.psf_source, olf_file=args.olf, basis_file=getattr(args, "basis", None),
                         pixel_pitch_mm=pixel_pitch_mm,
                         settings=settings, kernel_size=args.kernel, focus_m=focus_m,
                         custom_response=args.response is not None)
    say(src.message)
    return src


def _psf_from_source(args, src):
    """``dcdi psf`` served by the basis or the OLF: (kernel (3, k, k), pixel
    pitch), or None where the request lies outside its ranges (then traced,
    said why)."""
    from ..errors import InputRangeError
    from ..errors import ModelError
    try:
        kernel = src.library.kernels(args.field, args.depth)     # at the request's pitch
    except InputRangeError as e:            # OutsideTrainedRangeError included
        if args.psf_source == src.kind:
            raise ModelError(f"--psf-source {src.kind}: it cannot serve this request: {e}") from None
        say(f"PSFs traced instead: {e}")
        return None
    return kernel.astype("float32"), src.library.pixel_pitch_mm


def check_psf_pitch(lens, settings) -> float:
    """The pitch (mm) the PSFs are sampled at (--pixel-pitch, else the lens's
    sensor), refused before any tracing where the kernel (--kernel) cannot
    hold the lens's smallest spot or a pixel exceeds the sensor
    (``psf.compute.check_pixel_pitch``)."""
    from ..psf.compute import check_pixel_pitch, pixel_pitch_mm
    name = "pixel_pitch_mm" if settings.pixel_pitch_mm is not None else f"the pixel pitch of {lens.id}'s sensor"
    return check_pixel_pitch(lens, settings, pixel_pitch_mm(lens, settings), name=name)


def _write_kernel(path, kernel, pitch) -> None:
    import numpy as np

    from ..atomic import atomic_path
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            from ..io.npzfile import save_npz
            save_npz(f, {"psf": kernel, "pixel_pitch_mm": np.float64(pitch)}, compressed=False)


def cmd_psf(args) -> int:
    from ..psf.compute import check_psf_memory, pixel_pitch_mm, psf
    from ..psf.plots import depth_label, psf_grid_png
    from ..render.pictures import require_matplotlib
    lens = load_lens_with_aperture(args)
    check_output(args.out, "--out", suffix=".npz")
    check_output(args.png, "--png", suffix=".png")
    if args.png:
        require_matplotlib("--png")
    check_wavelength(lens, args)
    settings = psf_settings(args)
    check_psf_pitch(lens, settings)
    check_psf_memory(settings, 1, 1 if args.wavelength is not None else None)
    check_olf_file(args)
    extra = ("a field angle (--angle) was given; the OLF takes a field (--field)" if args.angle is not None else
             f"a monochromatic kernel (--wavelength {args.wavelength:g}) was asked for; the OLF learned the "
             "visible band" if args.wavelength is not None else None)
    src = choose_psf_source(args, lens, pixel_pitch_mm=pixel_pitch_mm(lens, settings), settings=settings,
                            focus_m=settings.focus_distance_m, extra_reason=extra)
    served = _psf_from_source(args, src) if src.library is not None else None
    if served is not None:
        kernel, pitch = served
        res = {"lens": lens.id, "depth_m": args.depth, "field": args.field, "kernel_size": kernel.shape[-1],
               "pixel_pitch_mm": pitch, "psf_source": src.kind,
               "olf_file": src.olf_file if src.kind == "olf" else None,
               "basis_file": src.basis_file if src.kind == "basis" else None,
               "raymap_file": src.raymap_file if src.kind == "raymap" else None,
               "channel_sums": [float(v) for v in kernel.sum(axis=(-1, -2))]}
        if args.out:
            _write_kernel(args.out, kernel, pitch)
        if args.png:
            psf_grid_png(kernel[None, None], [f"field {args.field}"], [depth_label(args.depth)], args.png,
                         f"{lens.name} ({ {'basis': 'PSF basis', 'raymap': 'ray map'}.get(src.kind, 'OLF')})", pitch)
        print_table_or_json(res, args.json)
        return 0
    r = psf(lens, depth_m=args.depth, field=args.field, angle_deg=args.angle, settings=settings,
            response=response(args), wavelength_nm=args.wavelength)
    pitch = pixel_pitch_mm(lens, settings)
    if r.zero_energy:
        raise no_ray_error(args, "the kernel would be empty")
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
        _write_kernel(args.out, r.psf, pitch)
    if args.png:
        at = f"field {args.field}" if args.field is not None else f"{args.angle} deg"
        psf_grid_png(r.psf[None, None], [at], [depth_label(args.depth)], args.png, f"{lens.name}", pitch)
    print_table_or_json(res, args.json)
    return 0


def cmd_psflib_build(args) -> int:
    from ..optics.lens import load_lens
    from ..progress import psf_progress
    from ..psf.library import LibraryGrid, PSFLibrary
    from ..render.request import check_library_memory
    lens = load_lens(args.lens)
    check_output(args.output, "-o", suffix=".npz")
    check_cache(args)
    grid = LibraryGrid(n_fields=args.fields, n_depths=args.depths, near_m=args.near, far_m=args.far)
    settings = psf_settings(args)
    check_psf_pitch(lens, settings)
    check_library_memory(settings, grid)
    lib = PSFLibrary.open(lens, settings, grid, response(args), cache=not args.no_cache)
    t = time.perf_counter()
    done = lib.build(progress=psf_progress(f"psflib {lens.id}"))
    lib.save(args.output)
    print(f"wrote {args.output}: {len(lib.depths_m)} depth bins x {len(lib.fields)} fields x 3 x "
          f"{lib.kernel_size} x {lib.kernel_size}; computed {len(done)} bins in "
          f"{time.perf_counter() - t:.1f} s ({len(lib.depths_m) - len(done)} from the cache)")
    return 0


def cmd_psflib_compress(args) -> int:
    from dataclasses import replace

    from ..optics.lens import load_lens
    from ..progress import psf_progress
    from ..psf.basis import SHIPPED_FOCUS_RECIPES, SHIPPED_RECIPES, BasisRecipe, build_store
    lens = load_lens(args.lens)
    check_output(args.output, "-o", suffix=".npz")
    check_cache(args)
    if args.focus_slices is not None:
        recipe = SHIPPED_FOCUS_RECIPES.get(lens.id, replace(SHIPPED_RECIPES.get(lens.id, BasisRecipe()), near_rays=None))
    else:
        recipe = SHIPPED_RECIPES.get(lens.id, BasisRecipe())
    over = {name: getattr(args, name) for name in ("rank", "rays", "n_fields", "n_depths", "pitch_factor",
                                                    "kernel_size", "near_rays", "focus_slices")
            if getattr(args, name) is not None}
    recipe = replace(recipe, **over)
    t = time.perf_counter()
    store = build_store(lens, recipe, cache_dir=False if args.no_cache else None,
                        progress=psf_progress(f"psflib {lens.id}"), log=say)
    store.save(args.output)
    from ..outputs import size_of
    print(f"wrote {args.output}: {lens.id}, rank {store.rank} of {store.kernel_size} x {store.kernel_size} px "
          f"kernels at {store.pixel_pitch_mm * 1000:.4g} um, {recipe.n_depths + 1} depth bins x {recipe.n_fields} "
          f"fields, {recipe.rays} rays" + (f" ({recipe.near_rays} to {recipe.near_until_m:g} m)" if recipe.near_rays
                                           else "")
          + (f", {recipe.focus_slices} focus distances (infinity to {recipe.focus_near_m:g} m)"
             if recipe.focus_slices else "") + f"; {size_of(args.output) / 1e6:.2f} MB; "
          f"{time.perf_counter() - t:.1f} s")
    return 0


def cmd_psflib_raymap(args) -> int:
    from dataclasses import replace

    from ..optics.lens import load_lens
    from ..progress import psf_progress
    from ..psf.raymap import RayMapRecipe, build
    lens = load_lens(args.lens)
    check_output(args.output, "-o", suffix=".npz")
    over = {name: getattr(args, name) for name in ("n_fields", "n_depths", "degree") if getattr(args, name) is not None}
    recipe = replace(RayMapRecipe(), **over)
    t = time.perf_counter()
    rm = build(lens, recipe, progress=psf_progress(f"ray map {lens.id}"))
    rm.save(args.output)
    from ..outputs import size_of
    print(f"wrote {args.output}: {lens.id}, {recipe.n_depths + 1} depths x {recipe.n_fields} fields x "
          f"{recipe.n_wavelengths} wavelengths, degree {recipe.degree}, {len(rm.clip_surfaces)} clipping surfaces; "
          f"{size_of(args.output) / 1e6:.2f} MB; {time.perf_counter() - t:.1f} s")
    return 0


def _is_basis(path) -> bool:
    """True for a PSF basis file (``dcdi psflib compress``), False for anything else."""
    from ..errors import DcdiError
    from ..io.model_npz import read_npz_with_meta
    try:
        meta, _ = read_npz_with_meta(path, "a PSF basis")          # bounded, checked (io.npzfile)
    except DcdiError:       # not readable as one: PSFLibrary.load says why
        return False
    return meta.get("format") == "dcdi-psf-basis"


def cmd_psflib_show(args) -> int:
    import numpy as np

    from ..optics.lens import load_lens
    from ..psf.library import LibraryGrid, PSFLibrary
    from ..psf.plots import depth_label, psf_grid_png
    from ..render.pictures import require_matplotlib
    from ..render.request import check_library_memory
    check_output(args.png, "--png", suffix=".png")
    require_matplotlib("--png")
    if args.library.endswith(".npz") and _is_basis(args.library):
        from ..psf.basis import BasisLibrary, BasisStore
        store = BasisStore.load(args.library)
        lib = BasisLibrary(store, load_lens(store.lens_id))
    elif args.library.endswith(".npz"):
        lib = PSFLibrary.load(args.library)
    else:
        lens = load_lens(args.library)
        check_cache()
        settings = psf_settings(args)
        check_psf_pitch(lens, settings)
        check_library_memory(settings)
        near = LibraryGrid().near_m
        if min(args.show_depths) < near:
            from ..errors import InputRangeError
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
        lib.warn_if_clipped(di)          # the file's clipped kernels say so, as the traced ones did
    else:
        kernels = lib.at(fields[:, None], depths[None, :], clamp_near=False)
    psf_grid_png(kernels, [f"field {f:.2f}" for f in fields], [depth_label(d) for d in depths],
                 args.png, f"PSF library: {lib.meta['lens_id']}", lib.pixel_pitch_mm)
    print(f"wrote {args.png}")
    return 0


def add_commands(sub) -> None:
    q = sub.add_parser("psf", help="the RGB PSF of one field and depth",
                       description="RGB PSF on the sensor's pixel grid, centred on the chief ray. " + UNITS)
    q.add_argument("lens", help="lens id or .toml path")
    add_field_options(q)
    q.add_argument("--wavelength", type=float, default=None, metavar="NM",
                   help="monochromatic kernel at NM nm (all three channels alike)")
    q.add_argument("--out", default=None, metavar="FILE.npz", help="write psf (3,k,k) and pixel_pitch_mm")
    q.add_argument("--png", default=None, metavar="FILE.png", help="write a picture of the kernel")
    q.add_argument("--json", action="store_true", help="print JSON")
    add_aperture_options(q)
    add_psf_options(q)
    add_psf_source_options(q)
    q.set_defaults(func=cmd_psf)

    q = sub.add_parser("psflib", help="PSF libraries (fields x depths): build, compress, show")
    psub = add_subcommands(q, "psflib_command")
    b = psub.add_parser("build", help="build a lens's PSF library and write it to a file",
                        description="Depth bins uniform in 1/depth from --near to --far, plus infinity. " + UNITS)
    b.add_argument("lens", help="lens id or .toml path")
    b.add_argument("-o", "--output", required=True, metavar="FILE.npz", help="the library file to write")
    b.add_argument("--fields", type=positive_int, default=64, help="fields over [0, 1] (default 64)")
    b.add_argument("--depths", type=positive_int, default=20, help="finite depth bins (default 20), plus infinity")
    b.add_argument("--near", type=float, default=0.7, metavar="M", help="nearest depth bin, metres (default 0.7)")
    b.add_argument("--far", type=float, default=10.0, metavar="M",
                   help="farthest finite bin, metres (default 10); farther = infinity")
    b.add_argument("--no-cache", action="store_true", help="do not read or write the cache")
    add_psf_options(b)
    b.set_defaults(func=cmd_psflib_build)
    c = psub.add_parser("compress", help="a lens's PSF basis: its library traced and stored as a low-rank "
                                         "basis + coefficients",
                        description="Traces the lens's library (or reads it from the cache) and writes its "
                                    "kernels as a per-channel SVD basis and coefficients (float16), the PSF "
                                    "source `--psf-source basis` serves. Defaults: the shipped recipe of the "
                                    "lens (dcdi_core/psf/basis.py SHIPPED_RECIPES), else rank 64, 256 rays, "
                                    "64 fields x 40 depth bins, 41 px. " + UNITS)
    c.add_argument("lens", help="lens id or .toml path")
    c.add_argument("-o", "--output", required=True, metavar="FILE.npz", help="the basis file to write")
    c.add_argument("--rank", type=positive_int, default=None, help="basis vectors kept per colour channel")
    c.add_argument("--rays", type=positive_int, default=None, metavar="N", help="pupil grid N x N of the trace")
    c.add_argument("--fields", dest="n_fields", type=positive_int, default=None, help="fields over [0, 1]")
    c.add_argument("--depths", dest="n_depths", type=positive_int, default=None,
                   help="finite depth bins, uniform in 1/depth over 0.7-10 m, plus infinity")
    c.add_argument("--pitch-factor", type=positive_int, default=None, metavar="N",
                   help="store at N x the sensor's pixel pitch (large blurs at a reduced resolution)")
    c.add_argument("--kernel", dest="kernel_size", type=positive_int, default=None, metavar="K",
                   help="kernel size K x K px at the stored pitch, odd")
    c.add_argument("--near-rays", type=positive_int, default=None, metavar="N",
                   help="pupil grid N x N for the depth bins at or nearer than 1 m (where the blur is largest "
                        "and a kernel's ray noise too)")
    c.add_argument("--focus-slices", type=positive_int, default=None, metavar="N",
                   help="a focus stack: the library traced at N focus distances, uniform in 1/focus from "
                        "infinity to 0.7 m, one basis for all (serves the lens refocused anywhere in that range; "
                        "defaults: the lens's shipped focus-stack recipe)")
    c.add_argument("--no-cache", action="store_true", help="do not read or write the PSF cache")
    c.set_defaults(func=cmd_psflib_compress)
    r = psub.add_parser("raymap", help="a lens's ray map: its rays as polynomials of the stop (any focus, "
                                       "f-number, blades and pixel pitch without tracing)",
                        description="Traces the lens as prescribed (wide open) at a grid of depths x fields x "
                                    "wavelengths and fits where each ray lands as polynomials of where it "
                                    "crosses the stop, the PSF source `--psf-source raymap` serves "
                                    "(dcdi_core/psf/raymap.py; defaults: RayMapRecipe, about a minute). " + UNITS)
    r.add_argument("lens", help="lens id or .toml path")
    r.add_argument("-o", "--output", required=True, metavar="FILE.npz", help="the ray map file to write")
    r.add_argument("--fields", dest="n_fields", type=positive_int, default=None, help="fields over [0, 1] (16)")
    r.add_argument("--depths", dest="n_depths", type=positive_int, default=None,
                   help="finite depths uniform in 1/depth from 0.4 m, plus infinity (16)")
    r.add_argument("--degree", type=positive_int, default=None, help="the landing point's polynomial degree (15)")
    r.set_defaults(func=cmd_psflib_raymap)
    s_ = psub.add_parser("show", help="a PNG grid of PSFs across field and depth")
    s_.add_argument("library", help="a library file (.npz from psflib build: its own settings and bins), a PSF "
                                    "basis (.npz from psflib compress), or a lens id or .toml path (its library "
                                    "with the options below, from the cache)")
    s_.add_argument("--png", required=True, metavar="FILE.png", help="the picture to write (PNG)")
    s_.add_argument("--show-fields", type=float, nargs="+", default=[0.0, 0.5, 0.7, 1.0], metavar="F",
                    help="fields to show, normalised image height in [0, 1] (default 0 0.5 0.7 1); from a "
                         "file, the nearest fields it holds")
    s_.add_argument("--show-depths", type=depth_value, nargs="+", default=[0.7, 1.0, 2.0, 5.0, math.inf], metavar="D",
                    help="depths to show, metres >= 0.7 or inf (default 0.7 1 2 5 inf); from a "
                         "file, the nearest computed bins")
    add_psf_options(s_)
    s_.set_defaults(func=cmd_psflib_show)
