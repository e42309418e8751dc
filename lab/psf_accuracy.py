"""`python -m lab report psf-accuracy LENS`: PSF error against build time.

Every approximation of the PSF is measured against a dense reference (512 x
512 rays, 31 wavelengths, float64, rays into the pixel they land in) at test sources across field
and depth: pupil grid, wavelength count, float32, sub-pixel binning, and the
library's depth-bin and field counts (interpolation error at depths and
fields between the bins). One parameter varies at a time, the others at the
defaults (`PSFSettings()`, `LibraryGrid()`), so each row reads "what this
choice costs and buys from the defaults". Errors: relative L1 (sum |P - R| /
sum R, mean over channels and sources) and PSNR (peak of R, worst source).
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dcdi_core.atomic import save_figure, write_text
from dcdi_core.optics.aiming import sources
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings, compute_sources, spectral_samples
from dcdi_core.psf.library import LibraryGrid, PSFLibrary

TEST_FIELDS = [0.0, 0.5, 1.0]
TEST_DEPTHS_M = [0.7, 2.0, math.inf]
# off-grid points for the interpolation sweeps
INTERP_DEPTHS_M = [0.83, 1.37, 3.1, 7.3]
INTERP_FIELDS = [0.137, 0.41, 0.77, 0.93]


def errors(p: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(relative L1 averaged over sources and channels, worst-source PSNR in dB)."""
    p = p.astype(np.float64)
    ref = ref.astype(np.float64)
    l1 = np.abs(p - ref).sum(axis=(-1, -2)) / np.maximum(ref.sum(axis=(-1, -2)), 1e-300)
    mse = ((p - ref) ** 2).mean(axis=(-3, -2, -1))
    peak = ref.max(axis=(-3, -2, -1))
    psnr = 10 * np.log10(np.maximum(peak, 1e-300) ** 2 / np.maximum(mse, 1e-300))
    return float(l1.mean()), float(psnr.min())


def _direct(lens, settings, fields, depths, response=None):
    """PSFs (n_field, n_depth, 3, k, k) computed directly, and the seconds it took."""
    t = time.perf_counter()
    aimed = sources(lens, depths, field=fields)
    wl, w = spectral_samples(settings, response)
    b = compute_sources(lens, aimed, settings, wl, w)
    return b.psf, time.perf_counter() - t, aimed.p.size


def run_report(lens_id: str, out: str | Path, *, quick: bool = False) -> int:
    lens = load_lens(lens_id)
    out = Path(out)
    base = PSFSettings()
    grid = LibraryGrid()
    if quick:
        ref_settings = replace(base, pupil_samples=96, n_wavelengths=15)
        sweeps = {"pupil_samples": [16, 32], "n_wavelengths": [3, 9], "precision": ["float32"],
                  "deposit_sigma_px": [0.25, 0.4714]}
        depth_bins, field_counts = [3, 6], [8, 16]
        combos = [dict(pupil_samples=32, n_wavelengths=5, precision="float32")]
    else:
        ref_settings = replace(base, pupil_samples=512, n_wavelengths=31)
        sweeps = {"pupil_samples": [16, 32, 64, 128, 256], "n_wavelengths": [3, 5, 9, 15, 31],
                  "precision": ["float32", "float64"],
                  "deposit_sigma_px": [0.0, 0.125, 0.25, 0.4714]}
        depth_bins, field_counts = [5, 10, 20, 40], [8, 16, 32, 64, 128]
        # candidate defaults: the sweeps show which errors dominate; these rows
        # measure the combinations, since one-at-a-time rows keep the others' error floor
        combos = [dict(pupil_samples=128, n_wavelengths=9, precision="float64"),
                  dict(pupil_samples=64, n_wavelengths=15, precision="float32"),
                  dict(pupil_samples=96, n_wavelengths=15, precision="float32"),
                  dict(pupil_samples=64, n_wavelengths=31, precision="float32"),
                  dict(pupil_samples=128, n_wavelengths=31, precision="float32")]
    print(f"psf-accuracy {lens.id}: reference {ref_settings.pupil_samples}^2 rays, "
          f"{ref_settings.n_wavelengths} wavelengths, float64 at {len(TEST_FIELDS)} fields x "
          f"{len(TEST_DEPTHS_M)} depths", flush=True)
    ref, t_ref, n_src = _direct(lens, ref_settings, TEST_FIELDS, TEST_DEPTHS_M)
    rows = [("reference", f"{ref_settings.pupil_samples} rays, {ref_settings.n_wavelengths} wl", 0.0,
             math.inf, t_ref / n_src)]
    defaults = base.as_dict()
    for name, values in sweeps.items():
        for v in values:
            s = replace(base, **{name: v})
            p, t, n = _direct(lens, s, TEST_FIELDS, TEST_DEPTHS_M)
            l1, psnr = errors(p, ref)
            tag = " (default)" if defaults[name] == v else ""
            rows.append((name, f"{v}{tag}", l1, psnr, t / n))
            print(f"  {name:<14} {str(v) + tag:<18} L1 {l1:.4f}  PSNR {psnr:6.2f} dB  {t / n * 1e3:7.1f} ms/PSF",
                  flush=True)
    for combo in combos:
        s = replace(base, **combo)
        p, t, n = _direct(lens, s, TEST_FIELDS, TEST_DEPTHS_M)
        l1, psnr = errors(p, ref)
        label = f"{combo['pupil_samples']} rays, {combo['n_wavelengths']} wl, {combo['precision']}"
        if all(defaults[k_] == v for k_, v in combo.items()):
            label += " (default)"
        rows.append(("combination", label, l1, psnr, t / n))
        print(f"  combination    {label:<34} L1 {l1:.4f}  PSNR {psnr:6.2f} dB  {t / n * 1e3:7.1f} ms/PSF",
              flush=True)
    # interpolation in depth: libraries with n bins (3 fields on the grid), against direct PSFs off-grid
    direct_d, _, _ = _direct(lens, base, TEST_FIELDS, INTERP_DEPTHS_M)
    for n in depth_bins:
        g = replace(grid, n_fields=len(TEST_FIELDS), n_depths=n)
        lib = PSFLibrary(lens, base, g, None)
        t = time.perf_counter()
        lib.build()
        t = time.perf_counter() - t
        p = lib.at(np.array(TEST_FIELDS)[:, None], np.array(INTERP_DEPTHS_M)[None, :])
        l1, psnr = errors(p, direct_d)
        per = t / lib.psf.shape[0] / lib.psf.shape[1]
        full = per * grid.n_fields * (n + 1)
        tag = " (default)" if n == grid.n_depths else ""
        rows.append(("depth bins", f"{n}{tag}", l1, psnr, per, full))
        print(f"  depth bins     {str(n) + tag:<18} L1 {l1:.4f}  PSNR {psnr:6.2f} dB  "
              f"library of {grid.n_fields} fields: {full:.1f} s (from {per * 1e3:.1f} ms/PSF)", flush=True)
    # interpolation in field: libraries with n fields (depth bins on the test depths)
    inf_only = [math.inf, 2.0]
    direct_f, _, _ = _direct(lens, base, INTERP_FIELDS, inf_only)
    for n in field_counts:
        g = replace(grid, n_fields=n, n_depths=2, near_m=2.0 / 1.0001, far_m=2.0 * 1.0001)
        lib = PSFLibrary(lens, base, g, None)
        t = time.perf_counter()
        lib.ensure(depth_m=[2.0, math.inf])
        t = time.perf_counter() - t
        p = lib.at(np.array(INTERP_FIELDS)[:, None], np.array([math.inf, 2.0])[None, :])
        l1, psnr = errors(p, direct_f)
        per = t / (2 * n)
        full = per * n * (grid.n_depths + 1)
        tag = " (default)" if n == grid.n_fields else ""
        rows.append(("fields", f"{n}{tag}", l1, psnr, per, full))
        print(f"  fields         {str(n) + tag:<18} L1 {l1:.4f}  PSNR {psnr:6.2f} dB  "
              f"library of {grid.n_depths + 1} bins: {full:.1f} s", flush=True)
    md = [f"# PSF accuracy against build time: {lens.id}", "",
          f"Reference: {ref_settings.pupil_samples}^2 rays over the real stop, {ref_settings.n_wavelengths} "
          f"wavelengths, float64, deposit sigma {ref_settings.deposit_sigma_px:g} px; test sources: fields {TEST_FIELDS} x depths "
          f"{TEST_DEPTHS_M} m. Interpolation rows: library PSFs at depths {INTERP_DEPTHS_M} m or fields "
          f"{INTERP_FIELDS} against direct PSFs there. Defaults: {defaults}.", "",
          "| parameter | value | rel. L1 | PSNR dB (worst) | time per PSF ms | full library s |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        full = f"{r[5]:.1f}" if len(r) > 5 else f"{r[4] * grid.n_fields * (grid.n_depths + 1):.1f}"
        psnr = "inf" if math.isinf(r[3]) else f"{r[3]:.2f}"
        md.append(f"| {r[0]} | {r[1]} | {r[2]:.5f} | {psnr} | {r[4] * 1e3:.2f} | {full} |")
    md += ["", "full library = time per PSF x 64 fields x 21 depth bins (measured per-PSF time; "
           "interpolation rows: the library built at that count)."]
    path_md = out / f"psf-accuracy-{lens.id}.md"
    write_text(path_md, "\n".join(md) + "\n")
    _plot(rows, out / f"psf-accuracy-{lens.id}.png", lens.id)
    print(f"wrote {path_md} and {out / f'psf-accuracy-{lens.id}.png'}")
    return 0


def _plot(rows, path, lens_id):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    groups = {}
    for r in rows[1:]:
        groups.setdefault(r[0], []).append(r)
    for name, rs in groups.items():
        x = [r[4] * 1e3 for r in rs]
        y = [max(r[2], 1e-6) for r in rs]
        ax.plot(x, y, "o-", label=name)
        for r, xi, yi in zip(rs, x, y):
            ax.annotate(str(r[1]).replace(" (default)", "*"), (xi, yi), fontsize=6,
                        textcoords="offset points", xytext=(3, 3))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per PSF (ms)")
    ax.set_ylabel("relative L1 error vs reference")
    ax.set_title(f"PSF error against run time: {lens_id} (* = default)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
