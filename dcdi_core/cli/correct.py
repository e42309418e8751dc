"""`dcdi correct` and `dcdi dof`: the user's verbs of the DCDI pipeline (undo
a lens's blur; give a capture another lens's depth of field).

Engine imports are inside the handlers: torch is loaded only once a command
has been checked and needs it.
"""
from __future__ import annotations

from .common import (UNITS, add_aperture_options, add_device_option, add_psf_options, add_psf_source_options, check_cache, check_olf_file,
                     check_output, depth_value, dump, in_cli_words, job_control, load_lens_with_aperture, positive_int,
                     psf_request, response,
                     say)
from ..psf.rule import rule_text
from .render import add_focus_options, add_rgbd_options, check_image_fits, quiet_input_warnings, render_inputs


# ------------------------------------------------------------------ the deconvolution's options
# the option each DeconvOptions / NoiseModel field is given by
DECONV_LABELS = {"weight": "--deconv-weight", "one_depth_m": "--one-depth", "method": "--deconv-method",
                 "full well (electrons)": "--noise-full-well", "read noise (electrons)": "--noise-read"}
DECONV_ONLY = ("deconv_weight", "deconv_method", "one_depth", "noise_full_well", "noise_read")
DOF_WORDS = {"model": "--dacn", "lens": "--camera"}


def _relabelled(make):
    """``make()``, a DeconvOptions / NoiseModel error renamed by the option the user gave."""
    from ..errors import InputRangeError
    try:
        return make()
    except InputRangeError as e:
        if e.name not in DECONV_LABELS:
            raise
        raise InputRangeError(DECONV_LABELS[e.name], e.value, e.allowed) from None


def deconv_options(args):
    """The ``correct.DeconvOptions`` of the command's options, checked
    (before any work): the noise of --noise-full-well / --noise-read (the
    other at the simulation's default), else estimated from the capture."""
    from ..correct import DeconvOptions, NoiseModel
    fw, rn = getattr(args, "noise_full_well", None), getattr(args, "noise_read", None)
    kw = {}
    if fw is not None or rn is not None:
        kw["noise"] = _relabelled(lambda: NoiseModel.sensor(10000.0 if fw is None else fw, 3.0 if rn is None else rn))
    if getattr(args, "deconv_weight", None) is not None:
        kw["weight"] = args.deconv_weight
    if getattr(args, "one_depth", None) is not None:
        kw["one_depth_m"] = args.one_depth
    if getattr(args, "deconv_method", None) is not None:
        kw["method"] = args.deconv_method
    return _relabelled(lambda: DeconvOptions(**kw))


def _refuse_deconv_only(args, method: str, reason: str) -> None:
    """A deconvolution's setting given where a network corrects: refused, saying why the network corrects."""
    given = [o for o in DECONV_ONLY if getattr(args, o, None) is not None]
    if method == "dacn" and given:
        from ..errors import InputRangeError
        raise InputRangeError("--" + given[0].replace("_", "-"), getattr(args, given[0]),
                              f"only with the deconvolution; the network corrects here ({reason}): give --method "
                              "deconv")


def _early_network(args, model_option: str) -> None:
    """A network asked for (--method dacn, or a network file): its device and the deconvolution's settings
    refused before any image is read."""
    model = getattr(args, model_option)
    if args.method == "dacn" or (model is not None and args.method == "auto"):
        _refuse_deconv_only(args, "dacn", f"--method {args.method}" if args.method == "dacn" else
                            f"a network was given: --{model_option} {model}")
        if hasattr(args, "device"):
            from ..models.common.distributed import resolve_device
            resolve_device(args.device)


def _correct_render(args, lens):
    """The capture on the lens's sensor (--pixel-pitch, --axis) and the PSF options, as a
    ``render.request.RenderRequest`` (`dacn correct` has none: None, the capture spans the sensor's
    diagonal, or what the file recorded)."""
    if lens is None or not hasattr(args, "image_pixel_pitch"):
        return None
    from ..render.request import RenderRequest
    from .common import psf_settings
    return RenderRequest(lens=lens, psf=psf_settings(args, sensor_focus=True), fit_kernel=not args.kernel,
                         image_pixel_pitch_mm=args.image_pixel_pitch, axis_px=tuple(args.axis) if args.axis else None)


def _refuse_missing_depth(args) -> None:
    """No --depth (and no --one-depth): refused, before any work."""
    if args.depth is None and getattr(args, "one_depth", None) is None:
        from ..errors import InputRangeError
        one = ", or --one-depth D for the deconvolution's depth-unaware baseline" if hasattr(args, "one_depth") else ""
        raise InputRangeError("--depth", None, "the scene's depth: give --depth DEPTH (metres: EXR 'Z', .npy, or "
                              "a 16-bit PNG in mm), e.g. the factory's depth/<id>.exr or a metric monocular "
                              f"estimate of the capture{one}")


def _correct_depth(args, shape):
    """The capture's depth map (metres), or None (--one-depth everywhere); refused when of another size."""
    if args.depth is None:
        return None
    from ..dataset.rgbd import read_any_depth
    from ..errors import InputRangeError
    depth = read_any_depth(args.depth)
    if depth.shape != tuple(shape):
        raise InputRangeError(f"depth map {args.depth}", depth.shape, f"{tuple(shape)} (the image {args.image})")
    return depth


def _given_deconv(args):
    """The deconvolution's options where any was given, else None (its defaults, and no refusal where a
    network corrects)."""
    return deconv_options(args) if any(getattr(args, o, None) is not None for o in DECONV_ONLY) else None


def _recorded(path):
    """What the capture file remembers of how it was made (None: nothing)."""
    from ..io.capture_record import read_record
    return read_record(path)


def cmd_correct(args) -> int:
    """`dcdi correct` and `dcdi dacn correct` (--method dacn, no deconvolution options)."""
    from ..app import CorrectRequest, correct
    from ..io.image_checks import check_image_output
    from ..io.images import read_image, write_image
    out = check_image_output(args.output)
    _refuse_missing_depth(args)
    lens = None
    if args.lens is not None:
        from ..optics.lens import load_lens
        # the deconvolution's lens at the capture's stop (`dacn correct` has no aperture options)
        lens = load_lens_with_aperture(args) if hasattr(args, "f_number") else load_lens(args.lens)
    CorrectRequest(None, None, lens, args.method, args.model)    # refused now, before any image is read
    _early_network(args, "model")
    deconvolves = lens is not None and args.method != "dacn" and args.model is None
    if deconvolves:                                     # its settings, PSF cache and OLF file checked now
        deconv_options(args)
        check_cache()
        check_olf_file(args)
    check_image_fits(args, "correct")
    image = read_image(args.image)
    depth = _correct_depth(args, image.shape[:2])
    request = CorrectRequest(image, depth, lens, args.method, args.model, render=_correct_render(args, lens),
                             deconv=_given_deconv(args) if hasattr(args, "deconv_weight") else None,
                             psf=psf_request(args, response(args)), tile=args.tile, overlap=args.overlap,
                             weights=args.weights, device=args.device, recorded=_recorded(args.image),
                             image_name=f"the image {args.image}")
    if args.method == "dacn" or args.model is not None:
        import torch
        torch.set_num_threads(args.threads)
    r = correct(request, job_control("dcdi correct", args))
    notes = in_cli_words(args, r.notes)
    for note in notes:
        say(f"note: {note}")
    write_image(out, r.image)
    print(dump({"output": str(out), "size": [image.shape[0], image.shape[1]],
                "lens": lens.id if lens is not None else r.info.get("trained_for"),
                "pixel_pitch_mm": r.geometry.pixel_pitch_mm if r.geometry is not None else None,
                "correction": in_cli_words(args, r.as_dict()),
                "seconds": {k: round(v, 3) for k, v in r.seconds.items()}, "notes": notes}))
    return 0


# ------------------------------------------------------------------ dcdi dof


def _refuse_correction_of_sharp(args) -> None:
    """--camera none with a correction's option: refused (a sharp image is not corrected)."""
    given = [f"--{o.replace('_', '-')}" for o in ("dacn", *DECONV_ONLY) if getattr(args, o, None) is not None]
    given += [f"--method {args.method}"] if args.method != "auto" else []
    if given:
        from ..errors import InputRangeError
        raise InputRangeError("--camera", "none", f"a lens: {given[0]} corrects a capture of a lens "
                              "(--camera none: a sharp image, no correction)")


def _camera_render(args, camera):
    """The capture on the camera's sensor: the geometry options (--pixel-pitch, --sensor-size,
    --axis) and the PSF settings, without the target's focus."""
    from .render import render_request
    return render_request(args, camera, sensor_focus=False)


def cmd_dof(args) -> int:
    from pathlib import Path

    from ..app import CorrectRequest, DofRequest, dof
    from ..io.images import write_depth, write_image
    from ..optics.lens import load_lens
    from .render import bokeh_request
    if args.side_by_side:                       # a picture needs matplotlib: refused before any work
        from ..render.pictures import require_matplotlib
        require_matplotlib("--side-by-side")
    camera = None if args.camera == "none" else load_lens(args.camera)
    if camera is not None:                              # refused before any image is read
        CorrectRequest(None, None, camera, args.method, args.dacn)
        _early_network(args, "dacn")
    else:
        _refuse_correction_of_sharp(args)
    deconv_options(args)
    lens, request, resp, img, depth = render_inputs(args, sensor_focus=False)
    if args.save_intermediates:
        for name in ("corrected.exr", "depth.exr"):
            check_output(str(Path(args.save_intermediates) / name), "--save-intermediates", image=True)
    correct_request = CorrectRequest(
        img, depth, camera, args.method, args.dacn,
        render=_camera_render(args, camera) if camera is not None else None, deconv=_given_deconv(args),
        psf=psf_request(args, resp), recorded=_recorded(args.image), image_name=f"the image {args.image}")
    if args.method == "dacn" or args.dacn is not None:
        import torch
        torch.set_num_threads(args.threads)
    with quiet_input_warnings():
        # app.dof decides the rest once: the capture's frame, the depth estimator by the rule, the target's plan
        r = dof(DofRequest(correct_request, bokeh_request(args, lens, request, resp, None, None), None,
                           args.uncertain_depth, depth_backend=args.depth_backend,
                           depth_checkpoint=args.depth_checkpoint, threads=args.threads),
                job_control("dcdi dof", args))
    notes = in_cli_words(args, r.notes)
    for note in notes:
        say(f"note: {note}")
    write_image(args.output, r.image)
    if args.save_intermediates:
        write_image(Path(args.save_intermediates) / "corrected.exr", r.corrected)
        write_depth(Path(args.save_intermediates) / "depth.exr", r.depth_m)
    if args.side_by_side:
        from ..models.dacn.evaluate import panel_strip
        from ..render.pictures import depth_panel
        write_image(args.side_by_side, panel_strip([img, r.corrected, depth_panel(r.depth_m), r.image]))
    print(dump({"output": args.output, "camera": args.camera, "lens": lens.id,
                "correction": in_cli_words(args, r.correction_dict()), "depth_source": r.depth_source,
                "psf_source": r.bokeh.source.kind, "seconds": {k: round(v, 3) for k, v in r.seconds.items()},
                "notes": notes}))
    return 0


# ------------------------------------------------------------------ the parsers
def add_method_option(q, what: str) -> None:
    """--method of `correct` and `dof` (``what``: the lens option that names the capture's lens)."""
    q.add_argument("--method", default="auto", metavar="auto|deconv|dacn",
                   help=f"how the capture is corrected: deconv, the deconvolution with the {what} lens's own PSFs "
                        "(any lens, no training); dacn, a trained network (the lens's shipped DACN or the one "
                        "given); auto (default), the shipped network only where it is recorded better than the "
                        "deconvolution on held-out captures (`python -m lab report correction`) and the image has the "
                        "pixel pitch it learned, else the deconvolution. A line on standard error says which "
                        "ran and why")


def add_deconv_options(q) -> None:
    """The deconvolution's settings (`correct` and `dof`)."""
    from ..correct import DeconvOptions
    d = DeconvOptions()
    q.add_argument("--deconv-weight", type=float, default=None, metavar="W",
                   help=f"the deconvolution's prior weight per unit of noise variance over the image's gradient "
                        f"power, > 0 (default {d.weight:g}): higher is smoother, lower sharper and noisier")
    q.add_argument("--deconv-method", choices=["wiener", "hqs"], default=None,
                   help="wiener (default: one filter a window) or hqs (half-quadratic splitting with a "
                        "total-variation prior: sharper edges for 3-4x the time)")
    q.add_argument("--noise-full-well", type=float, default=None, metavar="E",
                   help="the sensor's full well, electrons at 1.0 (with --noise-read: its noise model; a missing "
                        "one takes the simulation's default, 10000 or 3); default: the noise is estimated from "
                        "the capture")
    q.add_argument("--noise-read", type=float, default=None, metavar="E",
                   help="the sensor's read noise, electrons RMS (see --noise-full-well)")
    q.add_argument("--one-depth", type=depth_value, default=None, metavar="D",
                   help="the depth-unaware baseline: deconvolve with the PSFs of one depth D metres (or 'inf') "
                        "everywhere")


def correct_parser(subparsers, name: str, *, network_only: bool = False, **kw):
    """The parser of `correct`; ``network_only``: `dacn correct`, the
    network alone (no method, no deconvolution options)."""
    what = ("Correct a capture with a trained DACN (by default the shipped one of --lens): overlapping tiles "
            "cross-faded, memory bounded by one tile. " if network_only else
            "Undo a lens's blur: the deconvolution with the lens's own PSFs (any lens; depth- and field-aware, "
            f"PSFs from {rule_text()}), or a trained DACN (tiled), "
            "as --method chooses. Prints what it did as JSON. ")
    t = subparsers.add_parser(name, **kw, description=what + UNITS)
    t.add_argument("--image", required=True, help="the capture (EXR linear, or PNG/JPEG sRGB)")
    t.add_argument("--depth", default=None, help="its depth map in metres (EXR, .npy, 16-bit PNG in mm)")
    t.add_argument("--model", default=None,
                   help="a DACN run folder, its checkpoint.pt or an exported .npz (default: the shipped DACN of "
                        "--lens)")
    t.add_argument("--lens", default=None,
                   help="the lens that took the capture: its PSFs, or its shipped DACN without --model; with "
                        "--model, refuse a model trained for another lens")
    t.add_argument("-o", "--output", required=True, help="the corrected image (.exr, .png, .jpg)")
    if network_only:        # `dacn correct` has no --method: the deconvolution is `dcdi correct`'s
        t.set_defaults(method="dacn", words={"method": "dcdi correct --method"})
    else:
        add_method_option(t, "--lens")
        t.add_argument("--axis", type=float, nargs=2, default=None, metavar=("ROW", "COL"),
                       help="the optical axis's pixel position in the image (default: its centre)")
        add_deconv_options(t)
        add_aperture_options(t)
        add_psf_options(t, sensor_focus=True, render=True)
        add_psf_source_options(t)
    t.add_argument("--tile", type=positive_int, default=256, help="the network's tile size, px (default 256)")
    t.add_argument("--overlap", type=int, default=32, help="the network's tile overlap, px (default 32)")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights of the network")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    add_device_option(t, torchrun=False)
    t.set_defaults(func=cmd_correct)
    return t


def add_commands(sub) -> None:
    correct_parser(sub, "correct", help="undo a lens's blur: deconvolution with its PSFs (any lens) or a trained DACN")

    q = sub.add_parser("dof", help="DCDI end to end: a minimalist-lens capture -> another lens's depth of field",
                       description="Depth (given, or estimated from the capture), correction of the camera lens's "
                                   "aberrations (the deconvolution with its PSFs, or its trained DACN, as --method "
                                   "chooses), then the target lens's occlusion-aware bokeh with PSFs from "
                                   f"{rule_text()}. Prints what it did as JSON. " + UNITS)
    add_rgbd_options(q, sensor_focus=False, depth_required=False,
                     image_help="the capture (EXR linear, or PNG/JPEG sRGB)")
    q.add_argument("--camera", required=True,
                   help="the lens that took the capture (--method says how its blur is undone), or 'none' for a "
                        "sharp image")
    add_focus_options(q, "focus the target lens at D metres, or 'prescribed'")
    add_method_option(q, "--camera")
    q.add_argument("--dacn", default=None, metavar="MODEL",
                   help="the correction network (default: the shipped one of --camera, where --method picks a "
                        "network)")
    add_deconv_options(q)
    q.add_argument("--depth-backend", default=None, choices=["blur", "dcdi", "unidepth", "depth-anything-v2",
                                                              "depth-pro"],
                   help="the estimator when no --depth is given: blur (the depth from the capture's own blur "
                        "through --camera, numpy), dcdi (the shipped depth network of --camera, or "
                        "--depth-checkpoint), or a public one (default: blur where it is recorded 30 %% better "
                        "than a constant depth for --camera at the capture's pixel pitch (MOS-S1 and MOS-S2 at 12.2 um), "
                        "else the shipped network where it is (none), else --depth is asked for)")
    q.add_argument("--depth-checkpoint", default=None, metavar="PATH",
                   help="the estimator's checkpoint on this disk (never downloaded)")
    q.add_argument("--uncertain-depth", default="refuse", choices=["refuse", "accept"],
                   help="where the depth read from the capture's blur is too uncertain for the correction to beat "
                        "the uncorrected capture (its confidence; docs/depth.md): refuse (default: one line "
                        "asking for --depth, nothing written) or accept (run, with a note)")
    q.add_argument("--save-intermediates", default=None, metavar="DIR",
                   help="also write corrected.exr and depth.exr there")
    q.add_argument("--side-by-side", default=None, metavar="PNG", help="also write capture | corrected | depth | result")
    q.add_argument("--distort", action="store_true", help="also apply the target lens's distortion")
    q.add_argument("--plain", action="store_true", help="plain patch-wise blur instead of occlusion-aware layers")
    q.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    q.set_defaults(func=cmd_dof, words=DOF_WORDS)
