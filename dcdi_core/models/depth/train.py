"""Training the depth network (``arch.depthnet``) on DA2T pairs: the
capture in, the depth on the sensor out, L1 of log depth (a relative error,
the same weight for every distance; depths clamped to [0.1, 80] m, the sky
at 80 m), Adam with a cosine schedule, EMA; seeded, atomic
checkpoints and exact resume, the split by scene of the DACN's
(``dacn_loop.open_data``: test scenes never read).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...atomic import write_text
from .. import require_torch
from ..dacn.data import PairCrops, load_pair, pair_path
from ..common.metrics import depth_scores
from ..common.checkpoint import after_step, check_data, make_ema, open_run, restore, save_checkpoint, training_state, update
from ..dacn.train import centre_crop, open_data
from .config import DepthTrainConfig

torch = require_torch()
from .arch import DepthNet, log_target  # noqa: E402
from ..runtime.depth_encoding import DIOPTER_SCALE_M  # noqa: E402


@dataclass
class DepthResult:
    config: DepthTrainConfig
    model: object
    ema: object
    step: int
    seconds: float
    validation: dict = field(default_factory=dict)


def predict_depth(model, image) -> np.ndarray:
    """Metric depth (H, W) float32 of an (H, W, 3) image in [0, 1] (linear)."""
    x = torch.from_numpy(np.ascontiguousarray(np.clip(image, 0, 1).transpose(2, 0, 1), dtype=np.float32))[None]
    with torch.no_grad():
        log_d = model(x)[0, 0].numpy()
    return np.exp(log_d).astype(np.float32)


def evaluate_depth(model, root, ids, *, input: str = "capture", size: int = 0) -> dict:
    """Mean AbsRel / RMSE / delta1 over pairs ``ids`` (centre crops of
    ``size`` px if > 0), from their ``input`` image."""
    rows = []
    for pid in ids:
        p = load_pair(pair_path(root, pid))
        img, dep = np.array(getattr(p, input)), np.array(p.depth)
        if size:
            img, dep = centre_crop(img, size), centre_crop(dep, size)
        rows.append(depth_scores(predict_depth(model, img), dep))
    if not rows:
        return {}
    return {k: float(np.mean([r[k] for r in rows])) for k in ("abs_rel", "rmse", "delta1")}


def train_depth(config: DepthTrainConfig, run_dir, *, progress=None, on_step=None, log=None) -> DepthResult:
    say = log or (lambda s: None)
    run_dir, ckpt_path, settings, ck = open_run(run_dir, config)
    data = open_data(config)
    check_data(ck, ckpt_path, data.key, "data (pairs, their DA2T settings or the split)")
    write_text(run_dir / "config.json", config.to_json() + "\n")
    data.split.save(run_dir / "split.json")
    torch.manual_seed(config.seed)
    model = DepthNet(config.spec())
    ema = make_ema(model)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, betas=config.betas)
    rng = np.random.default_rng([config.seed, 17])
    crops = PairCrops([pair_path(data.root, p) for p in data.train], "diopter", augment=config.augment)
    step, history = restore(ck, model, ema, opt, rng, say=say, path=ckpt_path, iters=config.iters)

    def checkpoint():
        save_checkpoint(ckpt_path, training_state(
            step=step, settings=settings, config_json=config.to_json(), data_key=data.key, model=model, ema=ema,
            opt=opt, rng=rng, history=history, kind="depth", spec=json.dumps(config.spec().as_dict())))

    t0 = time.perf_counter()
    model.train()
    loss_v = float("nan")
    while step < config.iters:
        x, _, d = crops.sample(rng, config.batch, config.crop, input=config.input)
        x = torch.from_numpy(np.clip(x, 0, 1))
        # the crops' depth comes diopter-encoded (0.7 m / depth; 0: infinity or not imaged)
        metres = DIOPTER_SCALE_M / torch.from_numpy(d).clamp(min=1e-6)
        loss = (model(x) - log_target(metres)).abs().mean()
        update(opt, loss, config.lr_at(step), model, ema, config.ema_decay)
        step += 1
        loss_v = float(loss.detach())
        after_step(step, config.iters, config.checkpoint_every, loss_v, checkpoint, progress, on_step)
    seconds = time.perf_counter() - t0
    ema.eval()
    val = evaluate_depth(ema, data.root, data.val, input=config.input, size=256)
    with open(run_dir / "log.jsonl", "a", encoding="utf-8") as logf:
        logf.write(json.dumps({"step": step, "loss": loss_v, "seconds": seconds, "val_ema": val, "final": True}) + "\n")
    return DepthResult(config, model, ema, step, seconds, val)
