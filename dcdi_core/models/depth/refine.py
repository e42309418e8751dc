"""The learned refinement of the depth read from a capture's blur: data
(each DA2T pair's tile features and true tile depths), architecture (a few
3 x 3 convolutions over the tile grid, a residual on the evidence's log
depth), training (AbsRel over the tiles, Adam, seeded) and export (the .npz
that ``models.runtime.dfd_refine`` runs in numpy).

Units: depths in metres; the network works in log depth.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import require_torch
from ..runtime.dfd_refine import FORMAT, VERSION


@dataclass(frozen=True)
class RefineConfig:
    width: int = 32
    dilations: tuple = (1, 1, 2, 1)
    iters: int = 1500
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0


def pair_inputs(pairs_dir, lens, count: int = 10_000):
    """Per pair of ``pairs_dir`` (at most ``count``, by id): (id, the pair,
    its capture (H, W, 3) float32 with NaN as 0, its geometry on ``lens``'s
    sensor, ``lens``'s PSF library at that pitch)."""
    from ...app import PSFRequest, open_source
    from ...render.geometry import ImageGeometry
    from ..dacn.data import finished_pairs, load_pair, pair_path
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
    from ...dfd import estimate_depth
    from ...optics.lens import load_lens
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


def build(config: RefineConfig, channels: int):
    torch = require_torch()
    nn = torch.nn
    layers, c = [], channels
    for i, d in enumerate(config.dilations):
        last = i == len(config.dilations) - 1
        conv = nn.Conv2d(c, 1 if last else config.width, 3, padding=d, dilation=d, padding_mode="replicate")
        if last:                                          # starts as the evidence alone
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)
        layers += [conv] + ([] if last else [nn.ReLU()])
        c = config.width
    return nn.Sequential(*layers)


def _batch(items):
    torch = require_torch()
    x = torch.from_numpy(np.stack([it["features"] for it in items]))
    t = torch.from_numpy(np.stack([it["target"] for it in items]))
    return x, t


def abs_rel(model, x, t, log_channel: int):
    """Mean AbsRel over the tiles with a true depth."""
    torch = require_torch()
    z = torch.exp(x[:, log_channel] + model(x)[:, 0])
    ok = torch.isfinite(t)
    return (torch.abs(z[ok] - t[ok]) / t[ok]).mean()


def train(items: list[dict], config: RefineConfig, log_channel: int, log=print):
    """The model trained on ``items`` (all frames at once: a tile grid is
    small), seeded; returns (model, curve [(iteration, AbsRel)])."""
    torch = require_torch()
    torch.manual_seed(config.seed)
    x, t = _batch(items)
    model = build(config, x.shape[1])
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.iters, eta_min=config.lr * 0.01)
    gen = torch.Generator().manual_seed(config.seed)
    curve = []
    for it in range(config.iters):
        flip = torch.rand(1, generator=gen).item() < 0.5           # left-right: the field is symmetric
        xb, tb = (x.flip(-1), t.flip(-1)) if flip else (x, t)
        loss = abs_rel(model, xb, tb, log_channel)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if it % 100 == 0 or it == config.iters - 1:
            curve.append((it, loss.item()))
    return model, curve


def evaluate(model, items: list[dict], log_channel: int) -> float:
    torch = require_torch()
    x, t = _batch(items)
    with torch.no_grad():
        return float(abs_rel(model, x, t, log_channel))


def export(model, path, lens_id: str, config: RefineConfig, channels: int, log_channel: int, meta: dict) -> dict:
    """The .npz ``models.runtime.dfd_refine.DfdRefiner`` runs."""
    from ..runtime.npz import write_model_npz
    convs = [m for m in model if hasattr(m, "weight")]
    arrays = {}
    for i, conv in enumerate(convs):
        arrays[f"w{i}"] = conv.weight.detach().numpy().astype(np.float32)
        arrays[f"b{i}"] = conv.bias.detach().numpy().astype(np.float32)
    return write_model_npz(Path(path), {"format": FORMAT, "version": VERSION, "lens": lens_id,
                                        "channels": channels, "log_depth_channel": log_channel,
                                        "dilations": list(config.dilations), "config": config.__dict__, **meta},
                           arrays)
