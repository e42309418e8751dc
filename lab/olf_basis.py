"""`python -m lab olf-basis`: can a photographic lens's PSFs be learned at
the ray map's accuracy when the network gives the coefficients of a basis
of blur-scaled PSFs, not their pixels (docs/olf.md, "Learning from the ray
maps")?

In the blur-scaled frame (``lab.olf_frame``: each PSF drawn in an M x M
frame scaled to its thin-lens blur) the Nikkor 85 mm's PSFs are nearly one
shape; their principal components (an SVD of the training grid's frames,
mean removed) hold them in a few dozen numbers. Three stores of the same
training grid are scored on the same held-out points, in pixels, against
their 512-ray traces:

- ``basis``: each held-out frame projected on the basis (the basis's own
  error: the ceiling of anything that gives its coefficients);
- ``interpolated``: the coefficients interpolated linearly between the
  grid's points (Delaunay in field radius, inverse depth and inverse focus
  distance; the best non-learned store of the same samples);
- ``mlp``: an MLP from (field radius, inverse depth, inverse focus
  distance, signed thin-lens blur) to the coefficients, MSE (the frames'
  MSE: the basis is orthonormal), AdamW, cosine learning rate, EMA.

The frames are made once (``build_data`` with the pilot's settings,
``--focus-bins`` focus libraries; about 15 GB at 12 bins) and kept in
``OUT/frames.npz``; the held-out points are the pixel-head run's
(``--points RUN/points.npz``), traced once.

    python -m lab olf-basis --points OUT/olf-85-s0.npz.run/points.npz --seed 0 --out OUT/basis-s0 \\
        [--focus-bins 12] [--rank 64] [--iters 20000] [--width 256] [--layers 3]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from .olf_frame import PILOT, add_pilot_options, framed, from_frame


def frames(points: Path | None, seed: int, focus_bins: int, frame_px: int, out: Path, deposit_sigma_px: float = 0.0,
           log=print) -> dict:
    """The training grid's and the held-out points' frames (``OUT/frames.npz``,
    made once, with the settings that made them): inputs x (n, 3: field,
    inverse depth, inverse focus distance, 1/m), frames (n, 3, M, M), blur
    diameters (px); held-out pixels (n, 3, k, k)."""
    from dcdi_core.errors import CheckpointMismatchError
    from dcdi_core.models.olf.data import PSFDataConfig, build_data
    config = PSFDataConfig(seed=seed, focus_bins=focus_bins, deposit_sigma_px=deposit_sigma_px, **PILOT)
    settings = json.dumps({"data": config.as_dict(), "frame_px": frame_px}, sort_keys=True)
    cache = out / "frames.npz"
    if cache.exists():
        with np.load(cache) as z:
            if str(z["settings"]) != settings:
                was, now = json.loads(str(z["settings"])), json.loads(settings)
                diff = {k: (was["data"].get(k), now["data"].get(k)) for k in set(was["data"]) | set(now["data"])
                        if was["data"].get(k) != now["data"].get(k)}
                if was["frame_px"] != now["frame_px"]:
                    diff["frame_px"] = (was["frame_px"], now["frame_px"])
                raise CheckpointMismatchError(cache, diff)
            return {k: z[k] for k in z.files if k != "settings"}
    out.mkdir(parents=True, exist_ok=True)
    if points is not None and not (out / "points.npz").exists():
        shutil.copyfile(points, out / "points.npz")
    data = build_data(config, points_file=out / "points.npz", log=log)
    ls = data.lenses[0]
    scale = data.spec_kw["diopter_scale"]
    grid_x = ls.grid_x[:, :3].astype(np.float64) * [1.0, scale, scale]
    val_x = ls.val_x[:, :3].astype(np.float64) * [1.0, scale, scale]
    framed(data, frame_px)
    from dcdi_core.psf.sampling import blur_px_per_diopter
    bpd = blur_px_per_diopter(ls.lens, ls.pixel_pitch_mm)
    arrays = {"grid_x": grid_x, "grid_y": ls.grid_y, "grid_blur": bpd * np.abs(grid_x[:, 1] - grid_x[:, 2]),
              "val_x": val_x, "val_y": ls.val_y, "val_blur": ls.val_blur, "pixel_val": ls.pixel_val,
              "blur_px_per_diopter": np.float64(bpd)}
    np.savez(cache, settings=np.array(settings), **arrays)
    return arrays


def basis_of(frames_y: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean (D,), basis (rank, D) orthonormal rows) of the frames, flattened."""
    y = frames_y.reshape(len(frames_y), -1).astype(np.float64)
    mean = y.mean(axis=0)
    _, _, vt = np.linalg.svd(y - mean, full_matrices=False)
    return mean, vt[:rank]


def coefficients(frames_y, mean, basis) -> np.ndarray:
    return (frames_y.reshape(len(frames_y), -1).astype(np.float64) - mean) @ basis.T


def rebuilt(coef, mean, basis, shape) -> np.ndarray:
    return (coef @ basis + mean).reshape((len(coef),) + shape)


def features(x: np.ndarray, blur_px_per_diopter: float) -> np.ndarray:
    """The MLP's inputs: field radius, inverse depth and inverse focus distance
    (in units of 1/0.7 m), signed thin-lens blur (in 50 px)."""
    return np.stack([x[:, 0], x[:, 1] * 0.7, x[:, 2] * 0.7, (x[:, 1] - x[:, 2]) * blur_px_per_diopter / 50.0], -1)


def interpolated(grid_x, grid_c, val_x) -> np.ndarray:
    """The grid's coefficients interpolated linearly at the held-out inputs (nearest outside the hull)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    s = np.array([1.0, 0.7, 0.7])
    lin = LinearNDInterpolator(grid_x * s, grid_c)(val_x * s)
    near = NearestNDInterpolator(grid_x * s, grid_c)(val_x * s)
    return np.where(np.isnan(lin), near, lin)


def mlp(d_in: int, d_out: int, width: int, layers: int):
    """An MLP of ``layers`` SiLU layers of ``width``, and its EMA (0.999)."""
    import torch
    dims = [d_in] + [width] * layers
    mods = []
    for a, b in zip(dims[:-1], dims[1:]):
        mods += [torch.nn.Linear(a, b), torch.nn.SiLU()]
    net = torch.nn.Sequential(*mods, torch.nn.Linear(dims[-1], d_out))
    ema = torch.optim.swa_utils.AveragedModel(net, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(0.999))
    return net, ema


def fit_steps(net, ema, xt, yt, rng, iters: int, lr: float, batch: int, every: int):
    """Train ``net`` on (xt, yt) by MSE, AdamW without decay, the learning
    rate cosine from ``lr`` to lr / 100, the EMA updated each step; yields
    (step, the batch's loss) every ``every`` steps and at the last."""
    import torch
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=0.0)
    for step in range(1, iters + 1):
        for g in opt.param_groups:
            g["lr"] = lr * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * step / iters)))
        idx = torch.from_numpy(rng.integers(0, len(xt), batch))
        loss = ((net(xt[idx]) - yt[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        ema.update_parameters(net)
        if step % every == 0 or step == iters:
            yield step, loss.item()


def train_mlp(f_train, c_train, f_val, score, seed: int, iters: int, width: int, layers: int, lr: float,
              batch: int = 512, every: int = 1000, log=print) -> tuple[np.ndarray, list, float]:
    """An MLP f -> coefficients: (held-out coefficients of the EMA, curve, seconds)."""
    import torch
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net, ema = mlp(f_train.shape[1], c_train.shape[1], width, layers)
    xt, yt = torch.from_numpy(f_train).float(), torch.from_numpy(c_train).float()
    xv = torch.from_numpy(f_val).float()
    curve, t0 = [], time.process_time()
    for step, loss in fit_steps(net, ema, xt, yt, rng, iters, lr, batch, every):
        with torch.no_grad():
            pv = ema(xv).double().numpy()
        curve.append({"step": step, "loss": loss, "psnr_8bit": score(pv)["psnr_8bit"]})
        log(f"step {step}: loss {loss:.3e}, held-out {curve[-1]['psnr_8bit']:.2f} dB")
    with torch.no_grad():
        pv = ema(xv).double().numpy()
    return pv, curve, time.process_time() - t0


def run(points, seed: int, out: Path, frame_px: int = 41, focus_bins: int = 12, rank: int = 64, iters: int = 20000,
        width: int = 256, layers: int = 3, lr: float = 2e-3, deposit_sigma_px: float = 0.0, basis_ranks=(),
        log=print) -> dict:
    import torch
    from dcdi_core.models.common.metrics import psf_scores
    torch.set_num_threads(1)
    a = frames(points, seed, focus_bins, frame_px, out, deposit_sigma_px, log=log)
    shape = a["grid_y"].shape[1:]
    k = a["pixel_val"].shape[-1]
    ranks = sorted(set(basis_ranks or ()) | {rank})
    mean, full = basis_of(a["grid_y"], max(ranks))
    basis = full[:rank]

    def score(coef, vectors=None):
        f = np.maximum(rebuilt(coef, mean, basis if vectors is None else vectors, shape), 0.0)
        return psf_scores(from_frame(f, a["val_blur"], k), a["pixel_val"], scale="sum")

    bpd = float(a["blur_px_per_diopter"])
    result = {"seed": seed, "frame_px": frame_px, "focus_bins": focus_bins, "rank": rank, "grid": len(a["grid_y"]),
              "deposit_sigma_px": deposit_sigma_px,
              "held_out": len(a["val_y"]),
              "basis": score(coefficients(a["val_y"], mean, basis)),
              "interpolated": score(interpolated(a["grid_x"], coefficients(a["grid_y"], mean, basis), a["val_x"]))}
    result["basis_ranks"] = {str(r): score(coefficients(a["val_y"], mean, full[:r]), full[:r]) for r in ranks}
    result["frames"] = psf_scores(from_frame(a["val_y"], a["val_blur"], k), a["pixel_val"], scale="sum")
    log(f"basis {result['basis']['psnr_8bit']:.2f} dB, interpolated {result['interpolated']['psnr_8bit']:.2f} dB")
    if iters:
        pv, curve, cpu = train_mlp(features(a["grid_x"], bpd), coefficients(a["grid_y"], mean, basis),
                                   features(a["val_x"], bpd), score, seed, iters, width, layers, lr, log=log)
        n_par = sum(d_in * d_out + d_out for d_in, d_out in
                    zip([4] + [width] * layers, [width] * layers + [rank]))
        result.update(mlp=score(pv), curve=curve, cpu_s=cpu, iterations=iters, width=width, layers=layers, lr=lr,
                      parameters=n_par, basis_floats=int(basis.size + mean.size))
    (out / "result.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return result


def _spread(sc: dict) -> str:
    return (f"PSNR 8-bit mean {sc['psnr_8bit']:.2f}, median {sc['psnr_8bit_median']:.2f}, worst "
            f"{sc['psnr_8bit_worst']:.2f} dB, rel. L1 {sc['rel_l1']:.4f}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab olf-basis", description=__doc__.split("\n\n")[0])
    add_pilot_options(p, out="a folder: frames.npz (made once) and result.json", focus_bins=12)
    p.add_argument("--rank", type=int, default=64, help="basis vectors kept (default 64)")
    p.add_argument("--basis-rank", type=int, action="append", default=None, metavar="R", dest="basis_ranks",
                   help="also the basis's own error with R vectors (repeat): its table by rank")
    p.add_argument("--iters", type=int, default=20000, help="MLP iterations (default 20000; 0: no MLP)")
    p.add_argument("--width", type=int, default=256, help="MLP width (default 256)")
    p.add_argument("--layers", type=int, default=3, help="MLP hidden layers (default 3)")
    p.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (default 2e-3)")
    p.add_argument("--deposit-sigma", type=float, default=0.0, metavar="PX",
                   help="each ray's Gaussian spread in every PSF, learned and held out (default 0: the histogram; "
                        "the paper's 0.4714 needs its own held-out traces: no --points)")
    a = p.parse_args(argv)
    r = run(Path(a.points) if a.points else None, a.seed, Path(a.out), a.frame_px, a.focus_bins, a.rank, a.iters,
            a.width, a.layers, a.lr, a.deposit_sigma, a.basis_ranks or (), log=lambda t: print(t, file=sys.stderr))
    line = (f"seed {r['seed']}, rank {r['rank']}, {r['focus_bins']} focus bins, held-out PSNR 8-bit: basis "
            f"{r['basis']['psnr_8bit']:.2f} dB, interpolated {r['interpolated']['psnr_8bit']:.2f} dB")
    print("frames alone (the M x M frame and back): " + _spread(r["frames"]))
    for rk, sc in r["basis_ranks"].items():
        print(f"basis, rank {rk}: " + _spread(sc))
    print("interpolated: " + _spread(r["interpolated"]))
    if "mlp" in r:
        print("MLP: " + _spread(r["mlp"]))
    if "mlp" in r:
        line += (f", MLP {r['layers']} x {r['width']} ({r['parameters']} parameters, {r['iterations']} iterations, "
                 f"{r['cpu_s']:.0f} CPU s) {r['mlp']['psnr_8bit']:.2f} dB")
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
