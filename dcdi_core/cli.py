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


def cmd_bench(args) -> int:
    from . import bench
    return bench.run(args.what, args)


def cmd_demo(args) -> int:
    from . import demo
    return demo.run(args.out)


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

    q = sub.add_parser("bench", help="benchmarks (times, not tests)")
    q.add_argument("what", choices=["trace"], help="what to benchmark")
    q.add_argument("--rays", type=_positive_int, default=1 << 20, help="rays per trace (default 2^20)")
    q.add_argument("--repeat", type=_positive_int, default=3, help="timed repetitions (best is kept)")
    q.set_defaults(func=cmd_bench)

    q = sub.add_parser("demo", help="the demo job: lens reports and spot diagrams of all lenses")
    q.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    q.set_defaults(func=cmd_demo)
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
