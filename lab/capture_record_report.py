"""What a capture's record is worth: `dcdi correct` on a capture made by
`dcdi simulate --pixel-pitch 0.0122 --noise`, with its record, with the
same pixels but no record, and with no record but the pitch given.

    python -m lab capture-records [--out DIR] [--size H W] [--seed S]

Prints a markdown table: PSNR (dB) against the sharp image on the sensor of
the capture and of each correction, with the method the rule chose; and
whether the corrections with the record and with the pitch given are the
same bytes. Synthetic scene (``render.synthetic``), MOS-S1 and MOS-S2.
"""
from __future__ import annotations

import argparse
import json
from contextlib import redirect_stdout
from io import StringIO
from pathlib import Path

import numpy as np

from dcdi_core.outputs import scratch_folder


def _dcdi(*argv) -> dict:
    from dcdi_core.cli import main
    out = StringIO()
    with redirect_stdout(out):
        code = main([str(a) for a in argv])
    if code != 0:
        raise SystemExit(f"dcdi {' '.join(map(str, argv))} exited {code}")
    return json.loads(out.getvalue())


def _psnr(a, b) -> float:
    a, b = np.clip(a, 0, 1), np.clip(b, 0, 1)
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


def run(folder: Path, size=(240, 360), seed: int = 3, lenses=("mos-s1", "mos-s2")) -> list[str]:
    from dcdi_core.io.images import read_image, write_depth, write_image
    from dcdi_core.render.synthetic import synthetic_rgbd
    img, depth = synthetic_rgbd(*size, seed=seed)[:2]
    write_image(folder / "aif.exr", img)
    write_depth(folder / "depth.exr", depth)
    rows = ["| lens | capture dB | with its record | same pixels, no record | no record, pitch given | "
            "record = pitch given |", "|---|---|---|---|---|---|"]
    for lens in lenses:
        f = {k: folder / f"{k}-{lens}.exr" for k in ("cap", "sharp", "bare", "rec", "plain", "told")}
        _dcdi("simulate", "--image", folder / "aif.exr", "--depth", folder / "depth.exr", "--lens", lens,
              "--pixel-pitch", "0.0122", "--noise", "--seed", "0", "-o", f["cap"], "--sharp-out", f["sharp"])
        write_image(f["bare"], read_image(f["cap"]))            # the pixels without their record
        common = ["--depth", folder / "depth.exr", "--lens", lens]
        got = {"rec": _dcdi("correct", "--image", f["cap"], *common, "-o", f["rec"]),
               "plain": _dcdi("correct", "--image", f["bare"], *common, "-o", f["plain"]),
               "told": _dcdi("correct", "--image", f["bare"], *common, "--pixel-pitch", "0.0122",
                             "-o", f["told"])}
        sharp = read_image(f["sharp"])
        cells = [f"{got[k]['correction']['method']} {_psnr(read_image(f[k]), sharp):.2f}" for k in ("rec", "plain",
                                                                                                  "told")]
        same = bool(np.array_equal(read_image(f["rec"]), read_image(f["told"])))
        rows.append(f"| {lens} | {_psnr(read_image(f['cap']), sharp):.2f} | " + " | ".join(cells) + f" | {same} |")
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab capture-records", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    p.add_argument("--size", type=int, nargs=2, default=(240, 360), metavar=("H", "W"))
    p.add_argument("--seed", type=int, default=3)
    a = p.parse_args(argv)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        rows = run(a.out, tuple(a.size), a.seed)
    else:
        with scratch_folder() as tmp:
            rows = run(Path(tmp), tuple(a.size), a.seed)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
