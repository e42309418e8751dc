"""The demo's lens reports: for every lens in lenses/, its figures (text and
JSON), its spot diagrams and its RGB PSFs across field and depth."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from ..atomic import save_figure, write_text

FIELDS = [0.0, 0.5, 0.7, 1.0]
DEPTHS_M = [0.7, 1.0, 2.0, 5.0, 10.0, math.inf]
WAVELENGTHS_NM = [486.1327, 587.5618, 656.2725]   # F, d, C lines: blue, green, red
COLOURS = ["#1f5fff", "#2ca02c", "#e0301e"]


def spot_figure(lens, spots, path) -> None:
    """Spot diagrams (fields down, depths across), rays relative to the chief
    ray, one colour per wavelength, one scale for the whole lens (in um)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b = spots.bundle
    xy = b.position_mm[..., :2] * 1000.0
    valid = b.valid
    # relative to the design wavelength's chief ray, so lateral colour shows
    rel_y = xy[..., 1] - spots.chief_y_mm[:, :, 1, None, None] * 1000.0
    rel_x = xy[..., 0]
    extent = np.percentile(np.hypot(rel_x, rel_y)[valid], 99.5) if valid.any() else 1.0
    extent = float(max(extent, 1e-3)) * 1.1
    nf, nd = len(FIELDS), len(DEPTHS_M)
    fig, axes = plt.subplots(nf, nd, figsize=(2.1 * nd + 0.6, 2.1 * nf + 0.8), squeeze=False)
    for i in range(nf):
        for j in range(nd):
            ax = axes[i, j]
            for w, col in enumerate(COLOURS):
                m = valid[i, j, w]
                step = max(1, int(m.sum()) // 1500)   # a readable number of dots
                ax.scatter(rel_x[i, j, w][m][::step], rel_y[i, j, w][m][::step], s=0.3, c=col,
                           alpha=0.5, linewidths=0)
            ax.set_xlim(-extent, extent)
            ax.set_ylim(-extent, extent)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            rms = spots.rms_radius_mm[i, j, 1] * 1000.0
            vig = spots.vignetted_fraction[i, j, 1]
            ax.text(0.03, 0.03, f"rms {rms:.1f} um" + (f"\nvign {vig:.0%}" if vig > 0.005 else ""),
                    transform=ax.transAxes, fontsize=6.5)
            if i == 0:
                d = DEPTHS_M[j]
                ax.set_title("inf" if math.isinf(d) else f"{d:g} m", fontsize=9)
            if j == 0:
                ax.set_ylabel(f"field {FIELDS[i]:g}\n({FIELDS[i] * lens.sensor.semi_diagonal_mm:.2f} mm)", fontsize=8)
    fig.suptitle(f"{lens.name}\nspot diagrams, box = +-{extent:.0f} um about the chief ray; "
                 "blue 486 nm, green 588 nm, red 656 nm", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


PSF_FIELDS = [0.0, 0.5, 0.7, 1.0]
PSF_DEPTHS_M = [0.7, 1.0, 2.0, 5.0, math.inf]


def psf_figure(lens, path) -> str:
    """RGB PSFs across field and depth at the lens's pixel pitch, or at a
    coarser one where its blur would not fit the kernel (a photographic lens
    focused at infinity blurs a point at 0.7 m over hundreds of its sensor's
    pixels): the pitch that holds 99 % of the rays of the widest, said in
    the title; returns a one-line note of the pitch and what the kernel clips."""
    import warnings

    from ..optics.aiming import sources
    from ..psf.compute import PSFSettings, compute_sources, pixel_pitch_mm, spectral_samples
    from ..psf.plots import depth_label, psf_grid_png

    settings = PSFSettings()
    sensor_pitch = pixel_pitch_mm(lens, settings)
    aimed = sources(lens, PSF_DEPTHS_M, field=PSF_FIELDS)
    wl, w = spectral_samples(settings, None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b = compute_sources(lens, aimed, settings, wl, w)
        needed = int(b.kernel_size_needed.max())
        if needed > settings.kernel_size:
            settings = PSFSettings(pixel_pitch_mm=sensor_pitch * needed / settings.kernel_size)
            b = compute_sources(lens, aimed, settings, wl, w)
    pitch = pixel_pitch_mm(lens, settings)
    coarser = f", {pitch / sensor_pitch:.3g} x the sensor's pixels" if pitch > sensor_pitch else ""
    psf_grid_png(b.psf, [f"field {f:g}" for f in PSF_FIELDS], [depth_label(d) for d in PSF_DEPTHS_M],
                 path, f"{lens.name}: RGB PSFs ({pitch * 1000:.3g} um pixels{coarser})", pitch)
    worst = float(b.energy_outside.max())
    return (f"{pitch * 1000:.3g} um pixels{coarser}; kernel {settings.kernel_size} px clips at most {worst:.1%} "
            "of a channel's energy" + (f" (needs {int(b.kernel_size_needed.max())} px)" if worst > 0.01 else ""))


def lens_section(out: Path) -> list[str]:
    """Write every lens's report, figures JSON, spot diagrams and PSFs to
    ``out``; returns the report's lines (a table, one row per lens)."""
    from ..optics.analysis import spot_diagram
    from ..optics.lens import available_lenses, load_lens
    from ..optics.report import format_info, lens_info

    lines = ["## The lenses", "",
             "| lens | EFL mm (stated) | F/# (stated) | working F/# | FoV diagonal, real, deg | FoV stated, deg "
             "(its own measure: see lenses/README.md) | in-focus object m | spot rms on axis at inf, um |",
             "|---|---|---|---|---|---|---|---|"]
    for lid in available_lenses():
        t0 = time.perf_counter()
        lens = load_lens(lid)
        info = lens_info(lens)
        write_text(out / f"{lid}_report.txt", format_info(info) + "\n")
        write_text(out / f"{lid}_info.json", json.dumps(
            {k: (("inf" if v > 0 else "-inf") if isinstance(v, float) and math.isinf(v) else v)
             for k, v in info.items()}, indent=2) + "\n")
        spots = spot_diagram(lens, DEPTHS_M, WAVELENGTHS_NM, field=FIELDS, rays=64)
        spot_figure(lens, spots, out / f"{lid}_spots.png")
        clip = psf_figure(lens, out / f"{lid}_psfs.png")
        st = info["stated"]
        focus = info["in_focus_object_distance_m"]
        lines.append(
            f"| {lid} | {info['effective_focal_length_mm']:.3f} ({st.get('effective_focal_length_mm', '-')}) "
            f"| {info['f_number']:.3f} ({st.get('f_number', '-')}) | {info['working_f_number']:.3f} "
            f"| {info['field_of_view_deg']:.2f} | {st.get('field_of_view_deg', '-')} "
            f"| {focus if isinstance(focus, str) else round(focus, 4)} "
            f"| {spots.rms_radius_mm[0, -1, 1] * 1000:.2f} |")
        print(f"  {lid}: report, info JSON, spot diagrams and PSFs in {time.perf_counter() - t0:.1f} s; {clip}",
              flush=True)
    lines += ["", "Per lens: `<id>_report.txt` (text), `<id>_info.json` (all figures), "
              "`<id>_spots.png` (spot diagrams across field and depth), `<id>_psfs.png` (RGB PSFs "
              "across field and depth, traced, at the sensor's pixel pitch or a coarser one that holds the "
              "widest: its title says)."]
    return lines
