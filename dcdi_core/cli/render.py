"""`dcdi simulate` and `dcdi bokeh`: a lens's aberrations or depth of field on
an all-in-focus RGB-D image; the RGB-D options and checks `dcdi dof` shares.

Engine imports are inside the handlers so that `dcdi --help` stays fast.
"""
from __future__ import annotations

import contextlib
from dataclasses import replace

from .common import (UNITS, add_aperture_options, add_psf_options, add_psf_source_options, add_quality_option, check_cache, check_olf_file,
                     check_output, depth_value, dump, focus_value, in_cli_words, job_control, load_lens_with_aperture,
                     pixels, positive_int, psf_request,
                     psf_settings, response, say)


def add_rgbd_options(q, *, sensor_focus: bool, depth_required: bool = True,
                     image_help: str = "all-in-focus image (EXR linear, or PNG/JPEG sRGB)") -> None:
    """The image, depth map, lens, output, geometry and PSF options of a render.
    ``sensor_focus``: the PSF options' --focus moves the sensor (simulate);
    bokeh and dof add a --focus of their own."""
    from ..render.distortion import INTERPOLATIONS
    from ..render.base import DEFAULT_INTERPOLATION
    q.add_argument("--image", required=True, help=image_help)
    q.add_argument("--depth", required=depth_required,
                   help="metric depth map (EXR, metres from the lens; NaN/0/<0 invalid)"
                        + ("" if depth_required else "; without it, it is estimated from the image"))
    q.add_argument("--depth-channel", default=None, metavar="NAME",
                   help="the depth map's channel, e.g. Z or ViewLayer.Depth.Z (default: the first of "
                        "Z, depth.Z, Depth.V, V, depth, R, Y found)")
    q.add_argument("--lens", required=True, help="lens id or .toml path")
    q.add_argument("-o", "--output", required=True, help="output image (.exr linear, or .png)")
    q.add_argument("--patch", type=positive_int, default=16, help="patch size m in pixels (default 16)")
    q.add_argument("--sensor-size", type=positive_int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                   help="the sensor's frame in image pixels, centred on the optical axis, when the image is "
                        "larger (an over-scan render); the output has this size (default: the whole image)")
    q.add_argument("--axis", type=float, nargs=2, default=None, metavar=("ROW", "COL"),
                   help="the optical axis's pixel position in the image (default: its centre)")
    q.add_argument("--pinhole-focal-length", type=float, default=None, metavar="MM",
                   help="the focal length of the pinhole camera that rendered the image, on the scale of the image's "
                        "frame on the sensor (default: the lens's own, the scale of its ideal image; a camera framed "
                        "as the lens at a close focus has a longer one): where the lens moves the picture "
                        "(distortion, breathing) the image is read at this scale")
    q.add_argument("--wavelength", type=float, default=None, metavar="NM",
                   help="one wavelength for all three channels (monochrome, narrow-band); default: the "
                        "visible band weighted by the sensor's response")
    q.add_argument("--interpolation", default=DEFAULT_INTERPOLATION, choices=INTERPOLATIONS,
                   help=f"how the distortion warp resamples the image (default {DEFAULT_INTERPOLATION})")
    add_aperture_options(q)
    add_psf_options(q, sensor_focus=sensor_focus, render=True)
    add_psf_source_options(q)
    add_quality_option(q)


def add_focus_options(q, focus_help: str) -> None:
    """--keep NEAR FAR and/or --focus D (at least one): bokeh's and dof's depth
    of field (checked by BokehOptions)."""
    q.add_argument("--keep", type=float, nargs=2, metavar=("NEAR", "FAR"),
                   help="depth range kept sharp, metres (with --focus: the lens focused there, this range sharp)")
    q.add_argument("--focus", type=focus_value, metavar="D", help=focus_help)


def check_image_fits(args, job: str) -> None:
    """Refuse, from the headers alone (before any pixel is read), an image
    or depth map too large for this machine's memory for ``job``, or a depth
    map of another size than the image (``io.images.check_job_inputs``)."""
    from ..io.image_checks import check_job_inputs
    check_job_inputs(job, args.image, getattr(args, "depth", None), depth_channel=getattr(args, "depth_channel", None))


def read_rgbd(args, *, check_depth: bool = True):
    """The image and depth map (None without --depth), checked: same size; a
    depth map with no valid pixel refused; an implausible one (another unit)
    or negative light warned about, naming the files (render.inputs).
    ``check_depth``: False where the depth map is not used (--fixed-depth).
    An image too large for the memory is refused before it is read."""
    import warnings

    from ..io.images import read_depth, read_image
    from ..render.inputs import InputWarning, depth_problems, light_problems
    check_image_fits(args, getattr(args, "command", None))
    img = read_image(args.image)
    depth = None if args.depth is None else read_depth(args.depth, channel=args.depth_channel)
    if depth is not None and depth.shape != img.shape[:2]:
        from ..errors import InputRangeError
        raise InputRangeError(f"depth map {args.depth}", depth.shape, f"{img.shape[:2]} (the image {args.image})")
    problems = light_problems(img, args.image)
    if depth is not None and check_depth:
        problems += depth_problems(depth, args.depth)
    for msg in problems:
        warnings.warn(msg, InputWarning)
    return img, depth


def render_request(args, lens, *, sensor_focus: bool):
    """The engine's RenderRequest of a render command's options, checked."""
    from dataclasses import replace

    from ..render.request import RenderRequest
    settings = replace(psf_settings(args, sensor_focus=sensor_focus), wavelength_nm=args.wavelength)
    return RenderRequest(
        lens=lens, psf=settings, fit_kernel=not args.kernel, image_pixel_pitch_mm=args.image_pixel_pitch,
        sensor_size=tuple(args.sensor_size) if args.sensor_size else None,
        axis_px=tuple(args.axis) if args.axis else None, patch=args.patch, interpolation=args.interpolation,
        noise=getattr(args, "noise", False), full_well_electrons=getattr(args, "full_well", 10000.0),
        read_noise_electrons=getattr(args, "read_noise", 3.0), seed=getattr(args, "seed", None),
        perturb_seed=getattr(args, "perturb", None), perturb_fraction=getattr(args, "perturb_fraction", 0.10),
        fixed_depth_m=getattr(args, "fixed_depth", None),
        pinhole_focal_length_mm=getattr(args, "pinhole_focal_length", None))


def check_render_outputs(args) -> None:
    """Refuse, before any work, outputs that cannot be written or drawn
    (--side-by-side needs matplotlib), and an unwritable PSF cache."""
    check_output(args.output, "-o", image=True)
    check_output(getattr(args, "sharp_out", None), "--sharp-out", image=True)
    check_output(getattr(args, "side_by_side", None), "--side-by-side", suffix=".png")
    if getattr(args, "side_by_side", None):
        from ..render.pictures import require_matplotlib
        require_matplotlib("--side-by-side")
    check_cache()


def render_inputs(args, *, sensor_focus: bool):
    """Everything simulate and bokeh check before any work: the lens, the
    outputs, the request, the response file, the images (the geometry and
    its memory are the job's first step, ``app``'s plan, before any PSF).
    Returns (lens, request, response, image, depth)."""
    lens = load_lens_with_aperture(args)
    check_render_outputs(args)
    request = render_request(args, lens, sensor_focus=sensor_focus)
    resp = response(args)
    img, depth = read_rgbd(args, check_depth=request.fixed_depth_m is None)
    check_olf_file(args)
    return lens, request, resp, img, depth


@contextlib.contextmanager
def quiet_input_warnings():
    """The engine repeats the input warnings that read_rgbd gave (naming the files): silence its copies."""
    import warnings

    from ..render.inputs import InputWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        yield


def cmd_simulate(args) -> int:
    from ..app import SimulateRequest, simulate
    from ..io.images import write_image
    lens, request, resp, img, depth = render_inputs(args, sensor_focus=True)
    with quiet_input_warnings():
        r = simulate(SimulateRequest(img, depth, lens, request, psf_request(args, resp),
                                     distortion=not args.no_distortion, accelerator=args.accelerator,
                                     image_name=f"the image {args.image}"), job_control("dcdi simulate", args))
    for note in in_cli_words(args, r.notes):
        say(f"warning: {note}")
    write_image(args.output, r.image, record=r.record)
    if args.sharp_out:
        write_image(args.sharp_out, r.sharp)
    print(dump(in_cli_words(args, {"output": args.output, **r.info, "perturbation": r.perturbation,
                                   **_source_json(r.source), "seconds": {k: round(v, 3) for k, v in r.seconds.items()},
                                   "notes": r.notes})))
    return 0


def _source_json(source) -> dict:
    d = source.as_dict()
    return {"psf_source": d["psf_source"], "olf_file": d["olf_file"], "basis_file": d["basis_file"]}


def bokeh_request(args, lens, request, resp, img, depth, recorded=None):
    """The ``app.BokehRequest`` of `dcdi bokeh`'s options (and `dcdi dof`'s target lens); ``recorded``:
    the image file's capture record."""
    from ..app import BokehRequest
    return BokehRequest(img, depth, lens, keep=tuple(args.keep) if args.keep else None, focus_m=args.focus,
                        render=request, occlusion=not args.plain, distortion=args.distort,
                        multires=getattr(args, "multires", None), max_level=getattr(args, "max_level", None),
                        exact_layers=getattr(args, "exact_layers", False),
                        psf=replace(psf_request(args, resp), field_step_px=getattr(args, "field_step", None),
                                    focus_tolerance_px=getattr(args, "focus_tolerance", None)),
                        recorded=recorded, image_name=f"the image {args.image}")


def cmd_bokeh(args) -> int:
    from ..app import bokeh
    from ..io.images import write_image
    from ..render.multires import DEFAULT_MAX_LEVEL, check_multires
    check_multires(args.multires, DEFAULT_MAX_LEVEL if args.max_level is None else args.max_level, 16)
    lens, request, resp, img, depth = render_inputs(args, sensor_focus=False)
    with quiet_input_warnings():
        from ..io.capture_record import read_record
        r = bokeh(bokeh_request(args, lens, request, resp, img, depth, read_record(args.image)),
                  job_control("dcdi bokeh", args))
    notes = in_cli_words(args, r.notes)
    for note in notes:
        say(f"note: {note}")
    write_image(args.output, r.image)
    if args.side_by_side:
        from ..render.pictures import side_by_side
        keep = tuple(args.keep) if args.keep else None
        focus = (None if args.focus is None else "as prescribed" if args.focus == "prescribed"
                 else f"focus {args.focus:g} m")
        what = ", ".join(w for w in (focus, f"keep {keep[0]:g}-{keep[1]:g} m" if keep else None) if w)
        side_by_side(args.side_by_side, img if r.sharp is None else r.sharp,
                     depth if r.depth_m is None else r.depth_m, r.image, f"{lens.name}: {what}")
    print(dump(in_cli_words(args, {"output": args.output, "pixel_pitch_mm": float(r.geometry.pixel_pitch_mm),
                                   "axis_px": [float(c) for c in r.geometry.center_px], **r.info,
                                   **_source_json(r.source), "seconds": {k: round(v, 3) for k, v in r.seconds.items()},
                                   "notes": notes})))
    return 0


def add_commands(sub) -> None:
    q = sub.add_parser("simulate", help="depth-aware aberration simulation of an all-in-focus RGB-D image",
                       description="Patch-wise depth-aware PSF convolution, lens distortion, optional noise. " + UNITS)
    add_rgbd_options(q, sensor_focus=True)
    q.add_argument("--fixed-depth", type=depth_value, default=None, metavar="D",
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
    add_rgbd_options(q, sensor_focus=False)
    add_focus_options(q, "focus the lens at D metres, or 'prescribed': the lens as its prescription stands "
                         "(full physical defocus everywhere)")
    q.add_argument("--distort", action="store_true", help="also apply the lens's distortion (before the blur)")
    q.add_argument("--plain", action="store_true", help="plain patch-wise blur instead of occlusion-aware layers")
    q.add_argument("--multires", type=float, default=None, metavar="C",
                   help="multi-resolution blur: a patch whose kernel holds half its energy within a radius "
                        ">= C 2^s px is blurred at 1/2^s of the resolution (error and time against the exact path: "
                        "`python -m lab report simulation-accuracy`); default: every layer at full resolution")
    q.add_argument("--max-level", type=int, default=None, metavar="S",
                   help="with --multires: at most 1/2^S of the resolution (default 2)")
    q.add_argument("--exact-layers", action="store_true",
                   help="every depth layer at --patch with the tent, none merged (the former path: about twice "
                        "the time at the same error, docs/performance.md)")
    q.add_argument("--field-step", type=pixels, default=None, metavar="PX",
                   help="the PSFs' fields at most PX image pixels apart (fewer fields for a small image; the "
                        "add-on uses 16; error and time: `dcdi bench sampling`); default: the PSF source's grid")
    q.add_argument("--focus-tolerance", type=pixels, default=None, metavar="PX",
                   help="the focus may be rounded (in diopters, towards infinity) by at most PX pixels of blur "
                        "diameter, so that nearby focus distances share PSFs (the add-on uses 0.25); default: "
                        "the focus as given")
    q.add_argument("--side-by-side", default=None, metavar="PNG", help="also write input | depth | result")
    q.set_defaults(func=cmd_bokeh)
