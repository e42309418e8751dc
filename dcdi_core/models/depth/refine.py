"""The learned refinement of the depth read from a capture's blur:
architecture (a few 3 x 3 convolutions over the tile grid, a residual on
the evidence's log depth), training (AbsRel over the tiles of items
``{'features', 'target'}``, Adam, seeded) and export (the .npz that
``models.runtime.dfd_refine`` runs in numpy). The training data (each DA2T
pair's tile features and true tile depths) and the study that chose and
made the shipped files are the lab's (``lab/dfd_refine_study.py``).

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
    from ...io.model_npz import write_model_npz
    convs = [m for m in model if hasattr(m, "weight")]
    arrays = {}
    for i, conv in enumerate(convs):
        arrays[f"w{i}"] = conv.weight.detach().numpy().astype(np.float32)
        arrays[f"b{i}"] = conv.bias.detach().numpy().astype(np.float32)
    return write_model_npz(Path(path), {"format": FORMAT, "version": VERSION, "lens": lens_id,
                                        "channels": channels, "log_depth_channel": log_channel,
                                        "dilations": list(config.dilations), "config": config.__dict__, **meta},
                           arrays)
