"""What a factory data set cost to make: samples, wall and CPU seconds.

    python -m blender_addon.tools.dataset_cost DIR [DIR ...] [--pairs PAIRS ...]

Reads each factory folder's manifest (format: dcdi_core.dataset.factory_folder;
the seconds every sample recorded: scene build, Cycles render, EXR read,
the lens simulations, writes) and prints per recipe the sample count, mean wall and CPU seconds per sample and
the render's share; with ``--pairs``, the DA2T pair folders' counts per
lens. Wall seconds depend on what else the machine ran; CPU seconds less so.
No bpy: it reads JSON only.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from dcdi_core.dataset.factory_folder import FolderLayout, read_manifest  # noqa: E402


def manifest(folder: Path) -> list:
    """The finished samples' records of a factory folder (a torn last line does not count)."""
    p = FolderLayout(folder).manifest
    if not p.exists():
        raise SystemExit(f"dataset_cost: {p} does not exist (not a factory folder)")
    return read_manifest(p)[0]


def summary(records: list) -> dict:
    n = len(records)
    if not n:
        return {"samples": 0}
    wall = sum(r.get("seconds", 0.0) for r in records)
    cpu = sum(r.get("cpu_seconds", 0.0) for r in records)
    render = sum(r.get("stage_seconds", {}).get("cpu_render", 0.0) for r in records)
    return {"samples": n, "wall_s": wall / n, "cpu_s": cpu / n, "render_cpu_share": render / cpu if cpu else 0.0,
            "total_cpu_h": cpu / 3600}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m blender_addon.tools.dataset_cost",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--pairs", nargs="*", type=Path, default=[])
    args = ap.parse_args(argv)
    print("| folder | recipe | samples | wall s / sample | CPU s / sample | render share of CPU | CPU hours |")
    print("|---|---|---|---|---|---|---|")
    everything = []
    for f in args.folders:
        recs = manifest(f)
        everything += recs
        by = {}
        for r in recs:
            by.setdefault(r.get("recipe", "?"), []).append(r)
        for recipe, rs in sorted(by.items()):
            s = summary(rs)
            print(f"| {f.name} | {recipe} | {s['samples']} | {s['wall_s']:.1f} | {s['cpu_s']:.1f} | "
                  f"{100 * s['render_cpu_share']:.0f} % | {s['total_cpu_h']:.2f} |")
    s = summary(everything)
    if s["samples"]:
        print(f"| all | | {s['samples']} | {s['wall_s']:.1f} | {s['cpu_s']:.1f} | {100 * s['render_cpu_share']:.0f} % "
              f"| {s['total_cpu_h']:.2f} |")
    for p in args.pairs:
        lines = (p / "pairs.jsonl").read_text().splitlines() if (p / "pairs.jsonl").exists() else []
        lens = json.loads((p / "da2t.json").read_text())["lens"] if (p / "da2t.json").exists() else "?"
        print(f"pairs {p}: {len(lines)} DA2T pairs for {lens}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
