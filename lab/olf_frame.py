"""`python -m lab olf-frame`: does an Omni-Lens-Field learn a photographic
lens better when its head draws each PSF in coordinates scaled to the PSF's
thin-lens blur (docs/olf.md, "Learning from the ray maps")?

The study trains the shipped network (radial, ``dcdi olf train``'s data and
loop) on the same PSF data as a pixel-head run, with every target taken
into an M x M frame scaled to its blur (``lab.olf_report.frame_round_trip``'s
frame). The off-grid points are left out of the batches: their coordinates
are not kept, and the frame needs each PSF's blur. Its held-out points are
the pixel-head run's: the same ``points.npz``, given by
``--points RUN/points.npz`` and traced once. They are scored in pixels,
against the 512-ray traces, after the frame is taken back to the pixel grid.
The learning curve is in the frame (``log.jsonl``).

    python -m lab olf-frame --points OUT/olf-85-s0.npz.run/points.npz --seed 0 --out OUT/frame-s0 \\
        [--frame-px 41] [--iters 4000]

It trains the Nikkor 85 mm f/1.4 across focus at 75 um, with the pilot's
data settings (``PILOT``).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from .olf_report import FRAME_MARGIN, FRAME_PAD_PX, _linear_matrix

LENS = "nikkor-85mm-f1-4"
# the pixel-head pilot's data (docs/olf.md): the same config gives the same points file's key
PILOT = dict(lenses=(LENS,), focus_lenses=(LENS,), source="raymap", pixel_pitch_mm=0.075, held_out_rays=512)


def frame_step(blur_px, frame_px: int) -> np.ndarray:
    """Pixels between the frame's samples for each blur diameter (px)."""
    return np.maximum(1.0, (FRAME_MARGIN * np.asarray(blur_px, np.float64) + FRAME_PAD_PX) / frame_px)


def to_frame(kernels, blur_px, frame_px: int) -> np.ndarray:
    """Kernels (n, 3, k, k) in pixels -> (n, 3, M, M) in blur-scaled frames, each channel summing to 1."""
    from dcdi_core.psf.pitch import area_resample
    y = np.asarray(kernels, np.float64)
    k, m = y.shape[-1], int(frame_px)
    out = np.zeros(y.shape[:2] + (m, m))
    for i, step in enumerate(frame_step(blur_px, m)):
        if step > 1.0:
            out[i] = area_resample(y[i], 1.0, step, m)
        else:
            h = min(m, k) // 2
            out[i][:, m // 2 - h:m // 2 + h + 1, m // 2 - h:m // 2 + h + 1] = \
                y[i, :, k // 2 - h:k // 2 + h + 1, k // 2 - h:k // 2 + h + 1]
    s = out.sum(axis=(-1, -2), keepdims=True)
    return (out / np.where(s > 0, s, 1.0)).astype(np.float32)


def from_frame(frames, blur_px, k: int) -> np.ndarray:
    """(n, 3, M, M) blur-scaled frames -> (n, 3, k, k) pixel kernels (linear interpolation), summing to 1."""
    f = np.asarray(frames, np.float64)
    m = f.shape[-1]
    out = np.zeros(f.shape[:2] + (k, k))
    for i, step in enumerate(frame_step(blur_px, m)):
        u = _linear_matrix(k, m, step)
        back = np.einsum("im,cmn,jn->cij", u, np.maximum(f[i], 0.0), u)
        out[i] = back / np.maximum(back.sum(axis=(-1, -2), keepdims=True), 1e-300)
    return out


def _blur(lens, pitch_mm, depth_m, focus_m) -> np.ndarray:
    """Thin-lens blur diameters (px) at depths and focus distances (NaN: the prescribed focus)."""
    from dcdi_core.optics.paraxial import prescribed_focus_diopters
    from dcdi_core.psf.sampling import blur_px_per_diopter
    fm = np.asarray(focus_m, np.float64)
    focus_d = np.where(np.isnan(fm), prescribed_focus_diopters(lens), 1.0 / np.where(np.isnan(fm), 1.0, fm))
    with np.errstate(divide="ignore"):
        return blur_px_per_diopter(lens, pitch_mm) * np.abs(1.0 / np.asarray(depth_m, np.float64) - focus_d)


def framed(data, frame_px: int):
    """``data`` (``models.olf.data.OLFData``, radial) with its targets in
    blur-scaled frames: the grid's and the held-out points' (the pixel ones
    kept as ``pixel_val``), no off-grid points."""
    for ls in data.lenses:
        libs, nd, nf = ls.libraries, ls.libraries[0].grid.n_depths + 1, len(ls.libraries[0].fields)
        depth = np.broadcast_to(1.0 / np.maximum(libs[0].diopters, 1e-300)[None, :, None], (len(libs), nd, nf))
        depth = np.where(np.broadcast_to(libs[0].diopters[None, :, None], depth.shape) > 0, depth, np.inf)
        focus = np.broadcast_to(np.array([np.nan if f is None else f for f in ls.focus_values_m],
                                         np.float64)[:, None, None], depth.shape)
        zero = np.concatenate([lib.zero_energy.ravel() for lib in libs])
        blur = _blur(ls.lens, ls.pixel_pitch_mm, depth.ravel()[~zero], focus.ravel()[~zero])
        ls.grid_y = to_frame(ls.grid_y, blur, frame_px)
        ls.off_x, ls.off_y = ls.off_x[:0], np.zeros((0, 3, frame_px, frame_px), np.float32)
        c = ls.val_coords
        ls.val_blur = _blur(ls.lens, ls.pixel_pitch_mm, c["depth_m"], c.get("focus_m", np.full(len(ls.val_y), np.nan)))
        ls.pixel_val = ls.val_y
        ls.val_y = to_frame(ls.val_y, ls.val_blur, frame_px)
        ls.kernel_size = frame_px
    data.spec_kw["kernel_sizes"] = tuple(frame_px for _ in data.lenses)
    return data


def run(points: Path | None, seed: int, out: Path, frame_px: int = 41, iters: int = 4000, focus_bins: int = 3,
        log=print) -> dict:
    """Train the study's network (module docstring) into ``out`` and score it."""
    import torch

    from dcdi_core.models.common.loop import train_network
    from dcdi_core.models.common.metrics import psf_scores
    from dcdi_core.models.olf.config import OLFTrainConfig
    from dcdi_core.models.olf.data import PSFDataConfig
    from dcdi_core.models.olf.train import OLFTraining, _groups_to_torch, predict

    class FrameTraining(OLFTraining):
        def open_data(self, run_dir, say):
            return framed(super().open_data(run_dir, say), frame_px)

    config = OLFTrainConfig(data=PSFDataConfig(seed=seed, focus_bins=focus_bins, **PILOT), size="tiny", iters=iters, lr=1e-3, seed=seed,
                            threads=1, checkpoint_every=500, validate_every=500)
    run_dir = out / "run"
    run_dir.mkdir(parents=True, exist_ok=True)
    if points is not None and not (run_dir / "points.npz").exists():
        shutil.copyfile(points, run_dir / "points.npz")       # the pixel run's traced points: not traced again
    torch.set_num_threads(1)
    r = train_network(FrameTraining(config), run_dir, log=log)
    ls = r.data.lenses[0]
    r.ema.eval()
    with torch.no_grad():
        (pred,) = predict(r.ema, _groups_to_torch(r.data.held_out()))
    pixels = from_frame(pred.double().numpy(), ls.val_blur, ls.pixel_val.shape[-1])
    result = {"seed": seed, "frame_px": frame_px, "focus_bins": focus_bins, "iterations": r.step, "seconds": r.seconds,
              "parameters": int(sum(p.numel() for p in r.ema.parameters())),
              "held_out_pixels": psf_scores(pixels, ls.pixel_val, scale="sum"),
              "curve": [{"step": h["step"], "psnr_8bit_frame": h["held_out_ema"]["psnr_8bit"]} for h in r.history]}
    (out / "result.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return result


def add_pilot_options(p, *, out: str, focus_bins: int) -> None:
    """The options of a study on the pilot's data: its points, seed, folder, frame and focus bins."""
    p.add_argument("--points", default=None,
                   help="the pixel-head run's points.npz (its held-out points, not traced again; its key must be "
                        "this run's: the same seed, focus bins and deposit); default: traced here")
    p.add_argument("--seed", type=int, default=0, help="the pixel-head run's seed (its points' key), and the study's")
    p.add_argument("--out", required=True, help=out)
    p.add_argument("--frame-px", type=int, default=41, help="the frame, M x M (default 41)")
    p.add_argument("--focus-bins", type=int, default=focus_bins,
                   help=f"focus libraries besides the prescribed (default {focus_bins})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab olf-frame", description=__doc__.split("\n\n")[0])
    add_pilot_options(p, out="a folder: the run and result.json", focus_bins=3)
    p.add_argument("--iters", type=int, default=4000, help="iterations (default 4000, the pilot's)")
    a = p.parse_args(argv)
    r = run(Path(a.points) if a.points else None, a.seed, Path(a.out), a.frame_px, a.iters, a.focus_bins,
            log=lambda t: print(t, file=sys.stderr))
    h = r["held_out_pixels"]
    print(f"seed {r['seed']}, {r['frame_px']} px frame, {r['focus_bins']} focus bins, {r['iterations']} iterations, {r['parameters']} parameters: "
          f"held-out in pixels PSNR {h['psnr_8bit']:.2f} dB (8-bit), SSIM {h['ssim_8bit']:.4f}, rel. L1 "
          f"{h['rel_l1']:.4f}; curve (frame) " + ", ".join(f"{c['step']}: {c['psnr_8bit_frame']:.2f}"
                                                         for c in r["curve"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
