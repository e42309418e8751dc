"""Does a learned refinement earn its place over the depth read from blur
alone? (`python -m lab dfd-refine-study`)

Per lens: DA2T pairs of training frames, of validation frames and of
held-out test frames (split by scene: the factory's seeds differ); on each
pair the estimator's tile features (``dfd.estimate.tile_features``). Rows,
AbsRel over the tiles with a true depth:

- ``constant (frame median)``: each frame's own median depth (an oracle);
- ``constant (training median)``: the training tiles' median depth;
- ``blur alone``: the estimator's own estimate;
- ``refined``: the refinement (``models.depth.refine``) trained on the
  training pairs, each seed;
- ``refined without the evidence``: the same network at the same budget
  fed only the capture's statistics (field, texture power, colour): what
  the scenes' look alone gives.

Then the pixels' AbsRel of blur alone and refined (seed 0) on the test
pairs, through the estimator's fill. ``--export`` writes seed 0's network.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


# ------------------------------------------------------------------ the data: tile features of DA2T pairs
def pair_inputs(pairs_dir, lens, count: int = 10_000):
    """Per pair of ``pairs_dir`` (at most ``count``, by id): (id, the pair,
    its capture (H, W, 3) float32 with NaN as 0, its geometry on ``lens``'s
    sensor, ``lens``'s PSF library at that pitch)."""
    from dcdi_core.psf.sources import PSFRequest, open_source
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.models.dacn.data import finished_pairs, load_pair, pair_path
    recs = finished_pairs(pairs_dir)
    for pid in sorted(recs)[:count]:
        pair = load_pair(pair_path(pairs_dir, pid), recs[pid])
        centre, pitch, _ = pair.geometry()
        capture = np.nan_to_num(np.asarray(pair.capture, np.float32))
        g = ImageGeometry.from_pixel_pitch(lens, *capture.shape[:2], pitch, centre)
        yield pid, pair, capture, g, open_source(lens, g, PSFRequest()).library


def pair_features(pairs_dir, lens_id: str, count: int = 10_000, options=None, log=print) -> list[dict]:
    """Per pair of ``pairs_dir`` (at most ``count``): the estimator's tile
    features, the true depth of each tile (the median of its pixels within
    the library's range; NaN where fewer than half are) and the scene."""
    from dcdi_core.dfd import estimate_depth
    from dcdi_core.optics.lens import load_lens
    out = []
    for pid, pair, capture, g, library in pair_inputs(pairs_dir, load_lens(lens_id), count):
        h, w = capture.shape[:2]
        pitch = g.pixel_pitch_mm
        est = estimate_depth(capture, library, g, options)
        s = est.info["tile_px"]
        nph, npw = est.tile_diopters.shape
        d = np.pad(np.asarray(pair.depth, np.float64), ((0, nph * s - h), (0, npw * s - w)), constant_values=np.nan)
        ok = np.isfinite(d) & (d >= library.grid.near_m) & (d <= library.grid.far_m)
        d = np.where(ok, d, np.nan).reshape(nph, s, npw, s).transpose(0, 2, 1, 3).reshape(nph, npw, -1)
        enough = ok.reshape(nph, s, npw, s).mean((1, 3)) >= 0.5
        with np.errstate(all="ignore"):
            target = np.where(enough, np.nanmedian(d, -1), np.nan)
        out.append({"id": pid, "features": est.tile_features, "pixel_pitch_mm": float(pitch),
                    "hypotheses_m": est.info["hypotheses_m"], "target": target.astype(np.float32),
                    "pixels": est.depth_m, "depth": np.asarray(pair.depth, np.float32)})
    log(f"  {lens_id}: features of {len(out)} pairs from {pairs_dir}")
    return out


# ------------------------------------------------------------------ the scores
def tile_abs_rel(items, pred) -> float:
    num, den = 0.0, 0
    for it, z in zip(items, pred):
        t = it["target"]
        ok = np.isfinite(t)
        num += float((np.abs(z[ok] - t[ok]) / t[ok]).sum())
        den += int(ok.sum())
    return num / max(den, 1)


def pixel_abs_rel(items, pixels) -> float:
    vals = []
    for it, d in zip(items, pixels):
        t = it["depth"]
        ok = np.isfinite(t) & (t >= 0.7) & (t <= 10.0)
        vals.append(np.abs(d[ok] - t[ok]) / t[ok])
    return float(np.concatenate(vals).mean())


def main(argv=None) -> int:
    from dcdi_core.dfd.estimate import FEATURES
    from dcdi_core.models import require_torch
    from dcdi_core.models.depth import refine as R
    p = argparse.ArgumentParser(prog="python -m lab dfd-refine-study", description=__doc__.split("\n\n")[0])
    p.add_argument("--lens", required=True)
    p.add_argument("--train", required=True, nargs="+", help="training pairs folders")
    p.add_argument("--val", required=True, nargs="+", help="validation pairs folders")
    p.add_argument("--test", required=True, nargs="+", help="held-out test pairs folders")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--iters", type=int, default=1500)
    p.add_argument("--out", required=True, help="folder for table.md, curves.json (and the export)")
    p.add_argument("--export", default=None, metavar="NPZ", help="write seed 0's network there")
    a = p.parse_args(argv)
    torch = require_torch()
    torch.set_num_threads(2)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sets = {name: [it for d in dirs for it in pair_features(d, a.lens)]
            for name, dirs in (("train", a.train), ("val", a.val), ("test", a.test))}
    k = sets["train"][0]["features"].shape[0] - (len(FEATURES) - 1)
    log_ch = k                                              # after the k posterior channels
    seconds_features = time.perf_counter() - t0
    median = float(np.nanmedian(np.concatenate([it["target"].ravel() for it in sets["train"]])))
    rows = {}
    for name in ("val", "test"):
        items = sets[name]
        rows.setdefault("constant (frame median)", {})[name] = tile_abs_rel(
            items, [np.full_like(it["target"], np.nanmedian(it["target"])) for it in items])
        rows.setdefault(f"constant (training median {median:.2f} m)", {})[name] = tile_abs_rel(
            items, [np.full_like(it["target"], median) for it in items])
        rows.setdefault("blur alone", {})[name] = tile_abs_rel(items, [np.exp(it["features"][log_ch]) for it in items])
    curves, models = {}, {}

    def without_evidence(it):
        """The features the scene's look gives (field, texture power, colour); the posterior and the
        confidence zeroed, the log depth the training median's."""
        f = it["features"].copy()
        f[:log_ch] = 0.0
        f[log_ch] = np.log(median)
        f[log_ch + 1] = 0.0
        return dict(it, features=f)

    for seed in a.seeds:
        config = R.RefineConfig(iters=a.iters, seed=seed)
        t = time.perf_counter()
        model, curve = R.train(sets["train"], config, log_ch)
        models[seed] = model
        curves[f"refined seed {seed}"] = curve
        for name in ("val", "test"):
            rows.setdefault(f"refined, seed {seed}", {})[name] = R.evaluate(model, sets[name], log_ch)
        rows[f"refined, seed {seed}"]["seconds"] = time.perf_counter() - t
        # the same budget without the evidence: what the scenes' look alone gives
        base, curve_b = R.train([without_evidence(it) for it in sets["train"]], config, log_ch)
        curves[f"without evidence seed {seed}"] = curve_b
        for name in ("val", "test"):
            rows.setdefault(f"refined without the evidence, seed {seed}", {})[name] = R.evaluate(
                base, [without_evidence(it) for it in sets[name]], log_ch)
    lines = [f"{a.lens}: {len(sets['train'])} training, {len(sets['val'])} validation, {len(sets['test'])} test "
             f"pairs; {a.iters} iterations; tile AbsRel", "", "| row | validation | test |", "|---|---|---|"]
    lines += [f"| {r} | {v['val']:.3f} | {v['test']:.3f} |" for r, v in rows.items()]
    if a.export is not None and a.seeds:
        R.export(models[a.seeds[0]], a.export, a.lens, R.RefineConfig(iters=a.iters, seed=a.seeds[0]),
                 sets["train"][0]["features"].shape[0], log_ch,
                 {"trained_on": [str(x) for x in a.train], "pixel_pitch_mm": sets["train"][0]["pixel_pitch_mm"], "tile_px": 32,
                  "hypotheses_m": sets["train"][0]["hypotheses_m"],
                  "validation_abs_rel": rows[f"refined, seed {a.seeds[0]}"]["val"]})
        from dcdi_core.dfd import estimate_depth
        from dcdi_core.models.runtime.dfd_refine import DfdRefiner
        from dcdi_core.optics.lens import load_lens
        refiner, lens = DfdRefiner(a.export), load_lens(a.lens)
        alone, refined = [], []
        for d in a.test:
            for _, _, cap, g, lib in pair_inputs(d, lens):
                alone.append(estimate_depth(cap, lib, g).depth_m)
                refined.append(estimate_depth(cap, lib, g, refine=refiner).depth_m)
        lines += ["", f"Pixels of the test pairs (AbsRel): blur alone {pixel_abs_rel(sets['test'], alone):.3f}, "
                      f"refined (seed {a.seeds[0]}, numpy runtime) {pixel_abs_rel(sets['test'], refined):.3f}"]
    lines += ["", f"features: {seconds_features:.0f} s"]
    text = "\n".join(lines) + "\n"
    (out / "table.md").write_text(text)
    (out / "curves.json").write_text(json.dumps(curves) + "\n")
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
