"""How the factory's scenes spread over depth: a table and a PNG per recipe.

    python -m blender_addon.tools.depth_histogram [--recipe room ...] [--seeds 8] [--resolution 120 160] [--png FILE.png]

Renders the depth (Cycles Z pass, 1 sample, no denoiser: only depth is
wanted, and the Z pass of one sample is the first hit's distance) of
``--seeds`` scenes of each recipe through the factory's camera (MOS-S1: its
focal length, sensor and entrance pupil) and reports the fraction of the
pixels in each depth band (metres from the lens's first vertex, planar):
below 0.7 m (clamped to 0.7 m by the simulation), 0.7-1, 1-2, 2-5, 5-10,
10 m and beyond (finite), and infinity (the world background: sky).
Every pixel of a factory render has a valid depth (> 0 or inf).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_addon.factory.render import RenderSettings, render_rgbd  # noqa: E402
from blender_addon.factory.samples import sample_seed  # noqa: E402

# band edges in metres; the last finite band is [10, inf), then infinity itself
EDGES_M = (0.7, 1.0, 2.0, 5.0, 10.0)
BANDS = ("<0.7", "0.7-1", "1-2", "2-5", "5-10", ">10", "inf")


def band_fractions(depth: np.ndarray) -> np.ndarray:
    """Fractions (7,) of the pixels of a depth map (metres, inf = background)
    in the bands of BANDS. Raises ValueError on an invalid depth (NaN, <= 0):
    the factory's renders have none."""
    d = np.asarray(depth, dtype=np.float64).ravel()
    if d.size == 0 or not (d > 0).all():
        raise ValueError("depth map: every value must be > 0 m or inf (got NaN, 0 or negative, or no pixel)")
    finite = np.isfinite(d)
    idx = np.searchsorted(np.asarray(EDGES_M), d[finite], side="right")   # 0: < 0.7, ..., 5: >= 10
    counts = np.bincount(idx, minlength=len(EDGES_M) + 1).astype(np.float64)
    return np.append(counts, (~finite).sum()) / d.size


def depth_histogram(recipes=("room", "tabletop", "street"), seeds: int = 8, height: int = 120, width: int = 160,
                    dataset_seed: int = 0):
    """Per recipe: (band fractions (7,) pooled over the first ``seeds``
    samples of the dataset seed, all depths concatenated (finite ones, m),
    (min, max) finite depth in m)."""
    from dcdi_core.optics.lens import load_lens

    lens = load_lens("mos-s1")
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f".dcdi-depth-{os.getpid()}.exr"
    fast = RenderSettings(samples=1, denoise=False)
    out = {}
    for r in recipes:
        depths = [render_rgbd(r, lens, sample_seed(dataset_seed, i), height, width, fast, tmp)[1]
                  for i in range(seeds)]
        d = np.stack(depths)
        fin = d[np.isfinite(d)]
        out[r] = (band_fractions(d), fin, (float(fin.min()), float(fin.max())) if fin.size else (math.nan, math.nan))
    return out


def table(hist: dict) -> str:
    """Markdown table: per recipe the percentage of pixels per band, and the
    pooled row (recipes weighted equally)."""
    lines = ["| recipe | " + " | ".join(f"{b} m" if b != "inf" else "inf" for b in BANDS) + " | min-max m |",
             "|---" * (len(BANDS) + 2) + "|"]
    for r, (f, _, (lo, hi)) in hist.items():
        lines.append(f"| {r} | " + " | ".join(f"{100 * v:.1f} %" for v in f) + f" | {lo:.2f}-{hi:.1f} |")
    pooled = np.mean([f for f, _, _ in hist.values()], axis=0)
    lines.append("| all (equal weight) | " + " | ".join(f"{100 * v:.1f} %" for v in pooled) + " | |")
    return "\n".join(lines)


def save_png(hist: dict, path) -> None:
    """Histograms of log depth, one panel per recipe, band edges marked;
    the infinite fraction is printed in the panel's title."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dcdi_core.atomic import save_figure

    fig, axes = plt.subplots(1, len(hist), figsize=(4.2 * len(hist), 3.2), squeeze=False)
    bins = np.logspace(np.log10(0.3), np.log10(200.0), 60)
    for ax, (r, (f, fin, _)) in zip(axes[0], hist.items()):
        n_all = fin.size / max(1e-12, 1.0 - f[-1])          # pixels including the infinite ones
        ax.hist(np.clip(fin, bins[0], bins[-1]), bins=bins, weights=np.full(fin.size, 1.0 / n_all), color="C0")
        for e in EDGES_M:
            ax.axvline(e, color="0.4", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_xlabel("depth from the first vertex (m)")
        ax.set_ylabel("fraction of pixels")
        ax.set_title(f"{r}: infinity {100 * f[-1]:.1f} %", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m blender_addon.tools.depth_histogram",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", action="append", default=None, help="recipe (repeat; default room, tabletop, street)")
    p.add_argument("--seeds", type=int, default=8, help="samples per recipe (indices 0..N-1 of --dataset-seed)")
    p.add_argument("--dataset-seed", type=int, default=0)
    p.add_argument("--resolution", type=int, nargs=2, default=[120, 160], metavar=("H", "W"))
    p.add_argument("--png", default=None, help="write the histograms to this PNG")
    a = p.parse_args(argv)
    if a.seeds < 1:
        p.error(f"--seeds must be >= 1, got {a.seeds}")
    hist = depth_histogram(a.recipe or ("room", "tabletop", "street"), a.seeds, *a.resolution, a.dataset_seed)
    print(f"depth bands (fraction of pixels; {a.seeds} seeds per recipe, {a.resolution[0]} x {a.resolution[1]}, "
          "metres from the first vertex of MOS-S1)")
    print(table(hist))
    if a.png:
        save_png(hist, a.png)
        print(f"wrote {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
