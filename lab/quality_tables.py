"""The error tables the planner plans by (``dcdi_core.psf.budget``): each
knob of the PSF work alone against the converged render, per lens and per
pixel pitch, measured by ``dcdi_core.bench.quality`` and written to
``dcdi_core/psf/data/quality/LENS.json`` (one file a lens, written whole or
not at all; a lens whose file exists is skipped unless --force, so a run
that stops resumes where it was).

    python -m lab quality-tables [--lenses ID ...] [--size H W ...] [--force | --augment]

Every lens at 270 x 480 and 540 x 960 takes about an hour on two cores.
"""
from __future__ import annotations

import json


def main(argv=None) -> int:
    import argparse
    from dcdi_core.atomic import atomic_path
    from dcdi_core.bench import quality
    from dcdi_core.optics.lens import load_lens, available_lenses
    from dcdi_core.psf.budget import QUALITY_DIR, table_path
    p = argparse.ArgumentParser(prog="python -m lab quality-tables", description=__doc__.split("\n\n")[0])
    p.add_argument("--lenses", nargs="+", default=None, help="lens ids (default: every shipped lens)")
    p.add_argument("--size", type=int, nargs=2, action="append", metavar=("H", "W"),
                   help="image sizes measured (default 270 x 480 and 540 x 960; repeat the option)")
    p.add_argument("--force", action="store_true", help="measure again a lens whose table exists")
    p.add_argument("--augment", action="store_true",
                   help="add to existing tables the knobs they lack (the blur's: coarse layers, kernel crop), measured alone")
    args = p.parse_args(argv)
    sizes = [tuple(s) for s in args.size] if args.size else list(quality.SIZES)
    QUALITY_DIR.mkdir(parents=True, exist_ok=True)
    for lens_id in args.lenses or available_lenses():
        lens = load_lens(lens_id)
        path = table_path(lens.id)
        if args.augment:
            if path.exists():
                _augment(lens, path)
            continue
        if path.exists() and not args.force:
            print(f"{path}: exists (--force measures it again)", flush=True)
            continue
        t = quality.table(lens, sizes, say=lambda s: print(s, flush=True))
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(t, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {path}", flush=True)
    return 0


def _augment(lens, path) -> None:
    """Measure the blur knobs ``path``'s table lacks at each of its sizes, and write it again whole."""
    from dcdi_core.atomic import atomic_path
    from dcdi_core.bench import quality
    from dcdi_core.render.synthetic import synthetic_rgbd
    table = json.loads(path.read_text(encoding="utf-8"))
    changed = False
    for row in table["sizes"]:
        missing = [k for k in quality.BLUR_LEVELS if k not in row["knobs"]]
        if not missing:
            continue
        img, depth = synthetic_rgbd(row["rows"], row["cols"])
        # every blur knob again, so that their seconds share one baseline
        knobs, blur_s = quality.measure_blur(lens, img, depth, table["source"], lambda s: print(s, flush=True),
                                             f"{row['cols']} x {row['rows']}")
        row["knobs"].update(knobs)
        row["blur_s"] = round(blur_s, 3)
        changed = True
    if changed:
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(table, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {path}", flush=True)
