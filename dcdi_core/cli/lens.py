"""`dcdi lens list|info|import` and `dcdi spot`: lens prescriptions and their
ray-traced spots.

Engine imports are inside the handlers so that `dcdi --help` stays fast.
"""
from __future__ import annotations

from .common import (UNITS, add_subcommands, check_output, check_wavelength, depth_value, dump,
                     positive_int)


def cmd_lens_list(args) -> int:
    from ..optics.lens import available_lenses, load_lens
    ids = available_lenses()
    width = max((len(i) for i in ids), default=0)          # the names in one column
    for lid in ids:
        lens = load_lens(lid)
        print(f"{lid:<{width}} {lens.name}  ({lens.path})")
    return 0


def cmd_lens_info(args) -> int:
    from ..optics.lens import load_lens
    from ..optics.report import format_info, lens_info
    lens = load_lens(args.lens)
    check_wavelength(lens, args)
    info = lens_info(lens, args.wavelength, real_rays=not args.paraxial_only)
    print(dump(info) if args.json else format_info(info))
    return 0


def cmd_lens_import(args) -> int:
    from ..optics.lens import Lens
    from ..optics.zemax import read_zmx, write_toml
    check_output(args.output, "-o", suffix=".toml")
    d = read_zmx(args.file)
    if args.id:
        d["id"] = args.id
    Lens.from_dict(d, args.file)           # validate before anything is written
    write_toml(d, args.output)
    print(f"wrote {args.output} ({len(d['surface'])} surfaces)")
    return 0


def where(args):
    """(option, value) of the field asked for: --field or --angle."""
    return ("--field", args.field) if args.field is not None else ("--angle", args.angle)


def no_ray_error(args, what: str):
    from ..errors import InputRangeError
    return InputRangeError(*where(args), "a field some ray of which reaches the sensor (no ray of this one "
                           f"does: fully vignetted or beyond the image circle; {what})")


def cmd_spot(args) -> int:
    import numpy as np

    from ..memory import check_fits
    from ..optics.analysis import spot_diagram
    from ..optics.lens import load_lens
    from ..psf.compute import BYTES_PER_RAY, stop_ray_count
    lens = load_lens(args.lens)
    check_wavelength(lens, args)
    check_fits(stop_ray_count(args.rays) * BYTES_PER_RAY["float64"] * 2, f"spot --rays {args.rays} "
               f"({args.rays} x {args.rays} rays)", "lower --rays (memory grows as its square)")
    kw = {"field": [args.field]} if args.field is not None else {"angle_deg": [args.angle]}
    s = spot_diagram(lens, [args.depth], [args.wavelength], rays=args.rays, **kw)
    if not s.aimed.ok[0, 0] or s.vignetted_fraction[0, 0, 0] >= 1.0:
        raise no_ray_error(args, "no spot")
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
        print(dump(res))
    else:
        for k, v in res.items():
            print(f"{k:<22} {v}")
    return 0


def add_field_options(q) -> None:
    """--field or --angle (one of them), and --depth: where a PSF or spot is."""
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--field", type=float, metavar="F", help="normalised image height (1 = sensor semi-diagonal)")
    g.add_argument("--angle", type=float, metavar="DEG", help="field angle in object space, degrees")
    q.add_argument("--depth", type=depth_value, required=True, metavar="D", help="object depth in metres, or inf")


def add_commands(sub) -> None:
    lens = sub.add_parser("lens", help="lens prescriptions: list, info, import",
                          description="Lens prescriptions. " + UNITS)
    lsub = add_subcommands(lens, "lens_command")
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
    add_field_options(q)
    q.add_argument("--wavelength", type=float, required=True, metavar="NM", help="wavelength in nm")
    q.add_argument("--rays", type=positive_int, default=128, metavar="N", help="pupil grid N x N (default 128)")
    q.add_argument("--json", action="store_true", help="print JSON")
    q.set_defaults(func=cmd_spot)
