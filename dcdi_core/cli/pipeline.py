"""`dcdi correct` and `dcdi dof`: the user's verbs of the DCDI pipeline (undo
a lens's blur; give a capture another lens's depth of field).

Engine imports are inside the handlers: torch is loaded only once a command
has been checked and needs it.
"""
from __future__ import annotations

import time

from .common import (UNITS, add_device_option, check_output, counter, positive_int, say)
from .render import add_focus_options, add_rgbd_options, quiet_input_warnings, render_inputs


def _shipped(kind: str, lens_id: str | None):
    """The shipped ``kind`` network file (models.registry) of ``lens_id``, or None."""
    from ..models.registry import network
    return network(kind).shipped_file(lens_id) if lens_id is not None else None


def _shipped_for(kind: str) -> str:
    from ..models.registry import network
    return ", ".join(network(kind).shipped_keys()) or "none"


def _correct_model(args) -> tuple[str, str | None]:
    """(model, lens it must have been trained for or None): --model and
    --lens, or the shipped DACN of --lens; refused, naming the lenses that
    have one."""
    if args.model is not None:
        return args.model, args.lens
    if args.lens is None:
        from ..errors import InputRangeError
        raise InputRangeError("--model", None, "a DACN run folder, checkpoint.pt or exported .npz, or --lens LENS "
                              f"for the lens's shipped DACN (shipped for: {_shipped_for('dacn')})")
    from ..optics.lens import load_lens
    lens_id = load_lens(args.lens).id
    path = _shipped("dacn", lens_id)
    if path is None:
        from ..models.errors import ModelError
        raise ModelError(f"no shipped DACN for lens {lens_id} (shipped for: {_shipped_for('dacn')}); "
                         "give --model MODEL (a DACN run folder, checkpoint.pt or exported .npz)")
    return str(path), lens_id


def cmd_correct(args) -> int:
    from ..io.images import check_image_output, read_image, write_image
    if args.depth is None:
        from ..errors import InputRangeError
        raise InputRangeError("--depth", None, "the scene's depth: give --depth DEPTH (metres: EXR 'Z', .npy, or a "
                              "16-bit PNG in mm), e.g. the factory's depth/<id>.exr or a metric monocular estimate "
                              "of the capture")
    out = check_image_output(args.output)
    model_path, lens = _correct_model(args)
    from ..models.common.distributed import resolve_device
    resolve_device(args.device)                         # refused before any image is read
    from ..dataset.rgbd import read_any_depth
    image = read_image(args.image)
    depth = read_any_depth(args.depth)
    import torch
    torch.set_num_threads(args.threads)
    from ..models.dacn.correct import correct, load_dacn
    model, info = load_dacn(model_path, weights=args.weights, device=args.device)
    trained = (info.get("da2t") or {}).get("lens")
    if lens is not None and trained is not None and lens != trained:
        from ..models.errors import ModelError
        raise ModelError(f"{model_path} was trained for lens {trained}, not {lens}")
    t0 = time.perf_counter()
    result = correct(model, image, depth, tile=args.tile, overlap=args.overlap, progress=counter("correct: tile"))
    write_image(out, result)
    print(f"wrote {out} ({image.shape[1]} x {image.shape[0]}, {time.perf_counter() - t0:.1f} s, "
          f"lens {trained or 'unknown'}, on {info['device']})")
    return 0


def _dof_networks(args, camera):
    """(estimator or None, DACN or None, its info) for `dcdi dof`, all loaded
    (and refused, by name) before any work."""
    from ..models.errors import ModelError
    estimator = corrector = info = None
    if args.depth is None:
        ck = args.depth_checkpoint
        if ck is None and args.depth_backend == "dcdi":
            ck = _shipped("depth", camera.id if camera is not None else None)
            if ck is None:
                raise ModelError("no depth map (--depth) and no shipped depth network for "
                                 f"{'a sharp image (--camera none)' if camera is None else camera.id} (shipped: "
                                 f"{_shipped_for('depth')}); give --depth, or --depth-backend with "
                                 "--depth-checkpoint")
        from ..models.depth.estimators import load_estimator
        opts = {"threads": args.threads} if args.depth_backend == "dcdi" else {}
        estimator = load_estimator(args.depth_backend, ck, **opts)
    if camera is not None:
        path = args.dacn or _shipped("dacn", camera.id)
        if path is None:
            raise ModelError(f"no shipped DACN for {camera.id} (shipped: {_shipped_for('dacn')});"
                             " give --dacn MODEL, or --camera none for a sharp image")
        from ..models.dacn.correct import load_dacn
        corrector, info = load_dacn(path)
        trained = (info.get("da2t") or {}).get("lens")
        if trained is not None and trained != camera.id:
            raise ModelError(f"{path} was trained for lens {trained}, not the camera {camera.id}")
    return estimator, corrector, info


def cmd_dof(args) -> int:
    from pathlib import Path

    from ..io.images import write_depth, write_image
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    camera = None if args.camera == "none" else load_lens(args.camera)
    lens, request, plan, resp, img, depth = render_inputs(args, sensor_focus=False)
    if args.save_intermediates:
        for name in ("corrected.exr", "depth.exr"):
            check_output(str(Path(args.save_intermediates) / name), "--save-intermediates", image=True)
    import torch
    torch.set_num_threads(args.threads)
    estimator, corrector, info = _dof_networks(args, camera)
    from ..pipeline import dof
    camera_pitch = ImageGeometry.full_sensor(camera, *img.shape[:2]).pixel_pitch_mm if camera is not None else None
    with quiet_input_warnings():
        r = dof(img, lens, keep=tuple(args.keep) if args.keep else None, focus_m=args.focus, depth_m=depth,
                estimator=estimator, corrector=corrector, corrector_info=info, camera_pitch_mm=camera_pitch,
                psf_source=args.psf_source, olf_file=args.olf, settings=plan.settings, geometry=plan.geometry,
                source_geometry=plan.source_geometry, response=resp, distortion=args.distort,
                interpolation=request.interpolation, patch=request.patch, occlusion=not args.plain,
                fit_kernel=request.fit_kernel)
    say(r.psf_message)
    for note in r.notes:
        say(f"note: {note}")
    write_image(args.output, r.image)
    if args.save_intermediates:
        write_image(Path(args.save_intermediates) / "corrected.exr", r.corrected)
        write_depth(Path(args.save_intermediates) / "depth.exr", r.depth_m)
    if args.side_by_side:
        from ..models.dacn.evaluate import panel_strip
        from ..render.pictures import depth_panel
        write_image(args.side_by_side, panel_strip([img, r.corrected, depth_panel(r.depth_m), r.image]))
    times = ", ".join(f"{k} {v:.2f} s" for k, v in r.seconds.items())
    print(f"wrote {args.output}: camera {args.camera}, depth {r.depth_source}, PSFs {r.psf_source}; {times}")
    return 0


def correct_parser(subparsers, name: str, **kw):
    """The parser of `correct` (top level and `dacn correct`)."""
    t = subparsers.add_parser(name, **kw,
                              description="Correct a capture with a trained DACN (by default the shipped one of "
                                          "--lens): overlapping tiles cross-faded, memory bounded by one tile. "
                                          + UNITS)
    t.add_argument("--image", required=True, help="the capture (EXR linear, or PNG/JPEG sRGB)")
    t.add_argument("--depth", default=None, help="its depth map in metres (EXR, .npy, 16-bit PNG in mm)")
    t.add_argument("--model", default=None,
                   help="a DACN run folder, its checkpoint.pt or an exported .npz (default: the shipped DACN of "
                        "--lens)")
    t.add_argument("--lens", default=None,
                   help="the lens that took the capture: its shipped DACN without --model; with --model, refuse "
                        "a model trained for another lens")
    t.add_argument("-o", "--output", required=True, help="the corrected image (.exr, .png, .jpg)")
    t.add_argument("--tile", type=positive_int, default=256, help="tile size, px (default 256)")
    t.add_argument("--overlap", type=int, default=32, help="tile overlap, px (default 32)")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    add_device_option(t, torchrun=False)
    t.set_defaults(func=cmd_correct)
    return t


def add_commands(sub) -> None:
    correct_parser(sub, "correct", help="undo a lens's blur with a trained DACN (tiled, any size)")

    q = sub.add_parser("dof", help="DCDI end to end: a minimalist-lens capture -> another lens's depth of field",
                       description="Depth (given, or estimated from the capture), correction of the camera lens's "
                                   "aberrations (DACN), then the target lens's occlusion-aware bokeh with PSFs from "
                                   "the Omni-Lens-Field where it covers the request, else traced. " + UNITS)
    add_rgbd_options(q, sensor_focus=False, depth_required=False,
                     image_help="the capture (EXR linear, or PNG/JPEG sRGB)")
    q.add_argument("--camera", required=True,
                   help="the lens that took the capture (its shipped DACN corrects it), or 'none' for a sharp image")
    add_focus_options(q, "focus the target lens at D metres, or 'prescribed'")
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
    q.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    q.set_defaults(func=cmd_dof)
