"""The iris on the PSFs: the defocus blur against the f-number, and the
blades' polygons.

For each lens, focused at 2 m, a point at 0.7 m (defocused) on the axis
and at field 0.7: the PSF traced (128 rays per pupil side, 9 wavelengths,
an 81 px kernel at the lens's sensor pitch) wide open and stopped down to
2, 4 and 8 times the wide-open f-number (``optics.aperture``). The table
gives each PSF's RMS radius (px, about its
centroid, of the green channel: the red and blue ones add the lens's lateral
colour, which the stop does not change), the ratios r(N) / r(4N)
(geometric defocus: 4; aberrations that do not scale with the pupil and the
pixel move it; '(pixel)' where r(4N) < 1 px: the pixel sets it) and the
seconds of a trace. With ``--out DIR``,
a picture of the 6P's defocused PSF with 0, 5, 6 and 9 blades at two
f-numbers is written there (``aperture_blades.png``).

Run ``python -m lab aperture [--out DIR]`` (under a minute on 2 cores;
docs/psf.md).
"""
from __future__ import annotations

import time

import numpy as np

FOCUS_M, DEPTH_M = 2.0, 0.7
FIELDS = (0.0, 0.7)
FACTORS = (1.0, 2.0, 4.0, 8.0)


def rms_radius_px(k: np.ndarray) -> float:
    """RMS radius (px) of a kernel (k, k) about its centroid."""
    k = k / max(float(k.sum()), 1e-30)
    n = k.shape[-1]
    yy, xx = np.mgrid[:n, :n]
    cy, cx = (k * yy).sum(), (k * xx).sum()
    return float(np.sqrt((k * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum()))


def _settings():
    from dcdi_core.psf.compute import PSFSettings
    return PSFSettings(kernel_size=81, pupil_samples=128, n_wavelengths=9, focus_distance_m=FOCUS_M)


def rows_for(lens_id: str) -> list[dict]:
    from dcdi_core.optics.aperture import Aperture, stopped_down, wide_open_f_number
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import psf
    lens = load_lens(lens_id)
    n0 = wide_open_f_number(lens)
    rows = []
    for field in FIELDS:
        radii, secs = {}, {}
        for f in FACTORS:
            stopped = stopped_down(lens, Aperture(n0 * f))
            t = time.perf_counter()
            radii[f] = rms_radius_px(psf(stopped, depth_m=DEPTH_M, field=field, settings=_settings()).psf[1])
            secs[f] = time.perf_counter() - t
        rows.append({"lens": lens_id, "field": field, "n0": n0, "radii": radii, "seconds": secs})
    return rows


def format_table(rows: list[dict]) -> str:
    head = " | ".join(f"r at {f:g} N0 px" for f in FACTORS)
    out = [f"| lens | field | N0 (wide open) | {head} | r(N0) / r(4 N0) | r(2 N0) / r(8 N0) | s a PSF |",
           "|---|---|---|" + "---|" * len(FACTORS) + "---|---|---|"]
    for r in rows:
        rad = r["radii"]
        out.append(f"| {r['lens']} | {r['field']:g} | {r['n0']:.3g} | "
                   + " | ".join(f"{rad[f]:.2f}" for f in FACTORS)
                   + f" | {_ratio(rad, 1.0)} | {_ratio(rad, 2.0)} | "
                     f"{np.mean(list(r['seconds'].values())):.2f} |")
    return "\n".join(out)


def _ratio(rad: dict, f: float) -> str:
    """r(f N0) / r(4 f N0), '(pixel)' where the stopped one is under a pixel."""
    small = rad[4 * f]
    return f"{rad[f] / small:.2f}" if small >= 1.0 else "(pixel)"


def blades_picture(path) -> None:
    """The 6P's defocused PSF (field 0) with 0, 5, 6 and 9 blades at 2 and 4 x its wide-open f-number."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from dcdi_core.optics.aperture import Aperture, stopped_down, wide_open_f_number
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import psf
    lens = load_lens("6p")
    n0 = wide_open_f_number(lens)
    blades, factors = (0, 5, 6, 9), (1.25, 2.5)
    fig, axes = plt.subplots(len(factors), len(blades), figsize=(2.2 * len(blades), 2.3 * len(factors)))
    for i, f in enumerate(factors):
        for j, b in enumerate(blades):
            k = psf(stopped_down(lens, Aperture(n0 * f, b, 0.0)), depth_m=DEPTH_M, field=0.0,
                    settings=_settings()).psf
            rgb = np.moveaxis(k, 0, -1)
            axes[i, j].imshow(np.clip(rgb / rgb.max(), 0, 1) ** 0.5)
            axes[i, j].set_title(f"f/{n0 * f:.2g}, {'round' if b == 0 else f'{b} blades'}", fontsize=9)
            axes[i, j].axis("off")
    fig.suptitle(f"6P focused at {FOCUS_M:g} m, a point at {DEPTH_M:g} m (81 px at 12.2 um; sqrt scale)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    import argparse
    from pathlib import Path
    p = argparse.ArgumentParser(prog="python -m lab aperture",
                                description="the iris on the PSFs: blur against f-number, blades (module docstring)")
    p.add_argument("--lens", action="append", default=None, help="lens id (repeat; default 6p, mos-s1, double-gauss)")
    p.add_argument("--out", default=None, help="folder for the blades' picture")
    args = p.parse_args(argv)
    rows = []
    for lens_id in args.lens or ["6p", "mos-s1", "double-gauss"]:
        rows += rows_for(lens_id)
    print(format_table(rows))
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        blades_picture(Path(args.out) / "aperture_blades.png")
        print(f"wrote {Path(args.out) / 'aperture_blades.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
