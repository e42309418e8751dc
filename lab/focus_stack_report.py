"""A focus stack's error against tracing, and its time: the PSFs of a lens
refocused between the stack's focus distances.

For each lens with a shipped focus stack (``psf.basis.SHIPPED_FOCUS_RECIPES``)
and each focus distance of a set off the stack's (uniform in diopters over
its range), kernels traced with 256 rays per pupil side on a grid of 9
fields x 12 depth bins and infinity (0.75-9 m: off the stack's bins) are the
reference. Scored against it at those points (each source interpolating to
them as the renderer does, ``PSFLibrary.at``):

- the focus stack as served (``BasisStore.at_focus``: each depth bin's
  defocus matched at both neighbouring focus distances);
- the same stack interpolated plainly (each bin's kernels at the two focus
  distances mixed as they are): what the defocus matching improves on;
- the default trace at that focus (64 rays, 21 depth bins x 64 fields): what
  served a refocused singlet before the stack.

PSNR on the paper's scale: each channel divided by the reference's peak, the
mean square error over the kernel's pixels and channels; mean and (worst)
over the points. Time: the PSFs of a 480 x 270 frame's Apply (all depth bins,
the fields ``psf.sampling.field_grid`` keeps at 16 px), from the stack
(interpolation, reconstruction, area resampling) and traced (64 rays), in
this process, wall and CPU seconds.

Run ``python -m lab focus-stack`` (about 9 minutes on 2 cores; docs/psf.md).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np

FOCUS_POINTS = 6                    # focus distances scored per lens
REF_RAYS = 256
REF_GRID = dict(n_fields=9, n_depths=12, near_m=0.75, far_m=9.0)
PREVIEW_WIDTH = 480                 # px: the add-on's Apply at 480 x 270


def _psnr(ref: np.ndarray, est: np.ndarray) -> np.ndarray:
    """Per kernel (..., 3, k, k): PSNR in dB with each channel scaled by the reference's peak."""
    pk = np.maximum(ref.max(axis=(-1, -2), keepdims=True), 1e-12)
    mse = (((ref - est) / pk) ** 2).mean(axis=(-1, -2, -3))
    return 10.0 * np.log10(1.0 / np.maximum(mse, 1e-20))


def _crop(k: np.ndarray, size: int) -> np.ndarray:
    """Kernels cropped (centred) or zero-padded to ``size``, each channel summing to 1."""
    n = k.shape[-1]
    if n > size:
        h = (n - size) // 2
        k = k[..., h:h + size, h:h + size]
    elif n < size:
        p = (size - n) // 2
        k = np.pad(k, [(0, 0)] * (k.ndim - 2) + [(p, p), (p, p)])
    s = k.sum(axis=(-1, -2), keepdims=True)
    return np.divide(k, s, out=np.zeros_like(k), where=s > 0)


def _traced(lens, settings, grid):
    from dcdi_core.psf.library import PSFLibrary
    lib = PSFLibrary(lens, settings, grid, None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lib.build()
    return lib


def score_lens(lens_id: str, n_focus: int = FOCUS_POINTS, log=print) -> list[dict]:
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.basis import BasisLibrary, BasisStore, shipped_store
    from dcdi_core.psf.library import LibraryGrid
    from dcdi_core.psf.pitch import resampled_size
    from dcdi_core.psf.sampling import field_grid
    lens = load_lens(lens_id)
    path = shipped_store(lens_id, focus_stack=True)
    store = BasisStore.load(path)
    fd = store.focus_diopters
    k = store.kernel_size
    ref_grid = LibraryGrid(**REF_GRID)
    fields, depths = np.meshgrid(ref_grid.fields, ref_grid.depths_m, indexing="ij")
    # focus distances off the stack's: the midpoints and quarter points of its steps, spread over its range
    cand = np.concatenate([fd[:-1] + q * np.diff(fd) for q in (0.5, 0.25, 0.75)])
    focus_d = np.sort(cand)[np.linspace(0, len(cand) - 1, n_focus).round().astype(int)]
    base = store.settings
    pitch = store.pixel_pitch_mm
    sensor = lens.sensor
    preview_pitch = pitch * sensor.resolution_px[1] / PREVIEW_WIDTH
    preview_grid = field_grid(LibraryGrid(), sensor.semi_diagonal_mm, preview_pitch, 16)
    rows = []
    for d in focus_d:
        focus = 1.0 / d
        ref = _traced(lens, replace(base, pupil_samples=REF_RAYS, focus_distance_m=focus), ref_grid)
        want = _crop(ref.at(fields, depths), k)
        served = BasisLibrary(store, lens, focus_m=focus).at(fields, depths)
        plain_store = store.at_focus(focus, match_defocus=False)
        plain = BasisLibrary(plain_store, lens).at(fields, depths)
        trace = _traced(lens, replace(base, pupil_samples=64, focus_distance_m=focus), LibraryGrid())
        traced = _crop(trace.at(fields, depths), k)
        # the time of a 480 x 270 Apply's PSFs: from the stack, and traced
        t0, c0 = time.perf_counter(), time.process_time()
        BasisLibrary(store, lens, focus_m=focus, pixel_pitch_mm=preview_pitch).build()
        stack_s, stack_cpu = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        _traced(lens, replace(base, pupil_samples=64, focus_distance_m=focus, pixel_pitch_mm=preview_pitch,
                              kernel_size=resampled_size(k, pitch, preview_pitch)), preview_grid)
        trace_s, trace_cpu = time.perf_counter() - t0, time.process_time() - c0
        row = {"lens": lens_id, "focus_m": focus, "stack": _psnr(want, served), "plain": _psnr(want, plain),
               "trace": _psnr(want, traced), "stack_s": stack_s, "stack_cpu": stack_cpu,
               "trace_s": trace_s, "trace_cpu": trace_cpu, "fields": preview_grid.n_fields}
        log(f"{lens_id} focus {focus:.3g} m: stack {row['stack'].mean():.2f} ({row['stack'].min():.2f}) dB, "
            f"plain {row['plain'].mean():.2f}, trace {row['trace'].mean():.2f}; PSFs at 480 px "
            f"{stack_s:.3f} s from the stack, {trace_s:.2f} s traced")
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    out = ["| lens | focus m | stack dB | plain interpolation dB | trace, 64 rays dB | PSFs at 480 x 270: stack s "
           "(CPU) | traced s (CPU) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['lens']} | {r['focus_m']:.3g} | {r['stack'].mean():.2f} ({r['stack'].min():.2f}) | "
                   f"{r['plain'].mean():.2f} ({r['plain'].min():.2f}) | {r['trace'].mean():.2f} "
                   f"({r['trace'].min():.2f}) | {r['stack_s']:.3f} ({r['stack_cpu']:.3f}) | "
                   f"{r['trace_s']:.2f} ({r['trace_cpu']:.2f}) |")
    return "\n".join(out)


def main(argv=None) -> int:
    import argparse
    from dcdi_core.psf.basis import SHIPPED_FOCUS_RECIPES
    p = argparse.ArgumentParser(prog="python -m lab focus-stack",
                                description="a focus stack's error against tracing, and its time (module docstring)")
    p.add_argument("--lens", action="append", choices=sorted(SHIPPED_FOCUS_RECIPES), default=None,
                   help="a lens with a shipped focus stack (repeat; default: all)")
    p.add_argument("--focus-points", type=int, default=FOCUS_POINTS, help="focus distances scored per lens")
    args = p.parse_args(argv)
    rows = []
    for lens_id in args.lens or sorted(SHIPPED_FOCUS_RECIPES):
        rows += score_lens(lens_id, args.focus_points)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
