"""The training loop of the Omni-Lens-Field: plain, seeded, resumable.

One run lives in a folder: ``config.json`` (the settings), ``points.npz``
(the traced off-grid and held-out PSFs, so a resumed run need not trace them
again), ``checkpoint.pt`` (written atomically every ``checkpoint_every``
iterations and at the end: weights, EMA weights, optimiser state, iteration,
the batch generator's and torch's RNG states) and ``log.jsonl``.

Same config, same seed, same thread count: the same weights, bit for bit;
a run killed at any point and started again with the same config resumes
from its last checkpoint and ends exactly where an uninterrupted run would.
A checkpoint written with other settings is refused, naming them.

Each step: a batch from ``OLFData.sample`` (lenses uniform; grid and
off-grid points), the network's PSFs, MSE on the paper's scale (prediction
and target divided by the target's per-channel peak), AdamW, learning rate
cosine from ``lr`` to ``lr_min`` over ``iters``, then the EMA of the weights.

``device`` (auto, cpu, cuda[:N]) and the number of processes (``torchrun
--nproc-per-node N``, ``distributed``) are not settings: a checkpoint resumes
on another device or world size. Under N processes each draws the same
global batch and trains on its N-th (``local_groups``); rank 0 alone writes
the run folder. The log records the device and world size.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from ...atomic import write_text
from .. import require_torch
from ..common.metrics import psf_scores
from .data import Batch, OLFData, build_data, data_key
from ..common.checkpoint import after_step, check_data, make_ema, open_run, restore, save_checkpoint, training_state, update
from .config import OLFTrainConfig
from ..common.distributed import Context, LossModule

torch = require_torch()
from .arch import OLF  # noqa: E402  (after the torch check)

@dataclass
class TrainResult:
    config: OLFTrainConfig
    spec: object
    model: object            # the trained OLF module
    ema: object              # its exponential moving average
    data: OLFData
    step: int
    seconds: float           # training time of the steps to ``step`` (over resumed sessions; data excluded)
    history: list = field(default_factory=list)
    held_out: dict = field(default_factory=dict)   # {"ema": scores, "model": scores}; rank 0 only
    where: dict = field(default_factory=dict)      # device and world size it ran on (the last session)


def cosine_lr(config: OLFTrainConfig, step: int) -> float:
    """Learning rate of update ``step`` (0-based): cosine from lr to lr_min."""
    t = min(step, config.iters) / config.iters
    return config.lr_min + (config.lr - config.lr_min) * 0.5 * (1.0 + math.cos(math.pi * t))


def _groups_to_torch(batch, device=None):
    def t(a):
        x = torch.from_numpy(np.ascontiguousarray(a))
        return x if device is None else x.to(device)
    return [(li, t(x), t(y), t(s)) for li, x, y, s in batch.groups]


def local_groups(groups: list, rows: slice) -> list:
    """The samples at ``rows`` of a batch's groups taken in order (a rank's
    share of the global batch); groups left empty are dropped."""
    out, at = [], 0
    for li, x, y, s in groups:
        lo, hi = max(rows.start - at, 0), min(rows.stop - at, len(y))
        if lo < hi:
            out.append((li, x[lo:hi], y[lo:hi], s[lo:hi]))
        at += len(y)
    return out


def predict(model, groups):
    """The network's PSFs for each group: list of (n, 3, k, k) tensors."""
    out = []
    for li, x, _, _ in groups:
        if model.spec.variant == "paper":
            out.append(model(x))
        else:
            out.append(model(x, li))
    return out


def loss_of(model, groups):
    """Mean over the batch of each sample's MSE on the paper's scale."""
    total, n = 0.0, 0
    for pred, (_, _, y, s) in zip(predict(model, groups), groups):
        d = (pred - y) / s[:, :, None, None]
        total = total + (d * d).mean(dim=(1, 2, 3)).sum()
        n += len(y)
    return total / n


def evaluate(model, data: OLFData) -> dict:
    """Scores (``metrics.psf_scores``) on the held-out points, per lens and
    their mean over lenses (on the model's device)."""
    model.eval()
    scale = "peak" if model.spec.variant == "paper" else "sum"
    per = {}
    device = next(model.parameters()).device
    with torch.no_grad():
        groups = _groups_to_torch(data.held_out(), device)
        for pred, (li, _, y, _) in zip(predict(model, groups), groups):
            per[data.lenses[li].lens.id] = psf_scores(pred.double().cpu().numpy(), y.cpu().numpy(), scale=scale)
    model.train()
    keys = [k for k in next(iter(per.values())) if k != "n"]
    mean = {k: (float(np.mean([v[k] for v in per.values()])) if all(v[k] is not None for v in per.values())
                else None) for k in keys}
    return {"mean": mean, "lenses": per}


def _init_heads_from_data(model, data: OLFData):
    """radial: each head's bias = log of the lens's mean grid PSF, so the
    untrained network already gives the mean kernel (deterministic)."""
    if model.spec.variant != "radial":
        return
    with torch.no_grad():
        for li, ls in enumerate(data.lenses):
            src = ls.grid_y if ls.grid_y is not None and len(ls.grid_y) else ls.off_y
            mean = src.astype(np.float64).mean(axis=0).reshape(-1)
            model.heads[li].bias.copy_(torch.from_numpy(np.log(mean + 1e-8)).float())


def train(config: OLFTrainConfig, run_dir, *, cache_dir=None, lenses: dict | None = None, progress=None,
          on_step=None, log=None, device: str = "cpu") -> TrainResult:
    """Train (or resume) the run in ``run_dir``. ``cache_dir``: the PSF
    library cache (None: the default; False: none). ``progress(step, iters,
    loss)`` after each step; ``on_step(step)`` too (an exception there stops
    the run as a kill would, after the step and before any later checkpoint).
    ``device``: auto, cpu, cuda or cuda:N (``distributed.resolve_device``);
    under torchrun the processes share each global batch (module docstring)."""
    ctx = Context.from_environment(device)
    try:
        result = _train(config, run_dir, ctx, cache_dir=cache_dir, lenses=lenses, progress=progress,
                        on_step=on_step, log=log)
    except BaseException:
        ctx.close(clean=False)
        raise
    ctx.close()
    return result


def _train(config: OLFTrainConfig, run_dir, ctx: Context, *, cache_dir, lenses, progress, on_step,
           log) -> TrainResult:
    say = (log or (lambda s: None)) if ctx.main else (lambda s: None)
    progress = progress if ctx.main else None
    rows = ctx.part(config.batch)                        # refused before any work
    run_dir, ckpt_path, settings, ck = open_run(run_dir, config)
    if ctx.main:
        write_text(run_dir / "config.json", config.to_json() + "\n")
    with ctx.main_first():                               # rank 0 traces and caches, the others read
        data = build_data(config.data, cache_dir=cache_dir, points_file=run_dir / "points.npz", lenses=lenses,
                          log=say)
    key = data_key(config.data, [ls.lens for ls in data.lenses])
    check_data(ck, ckpt_path, key, "data (a lens's optics or the PSF algorithm)")
    spec = data.spec(**config.arch())
    torch.manual_seed(config.seed)
    model = OLF(spec)
    _init_heads_from_data(model, data)
    model.to(ctx.device)
    ema = make_ema(model)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, betas=config.betas,
                            weight_decay=config.weight_decay)
    rng = np.random.default_rng([config.seed, 7])
    step, history = restore(ck, model, ema, opt, rng, say=say, path=ckpt_path, iters=config.iters)
    prior_s = 0.0 if ck is None else float(ck.get("seconds", 0.0))   # training time of the steps it holds
    # radial, several lenses: a rank's share may lack a lens, whose head is then unused there
    step_loss = ctx.wrap(LossModule(model, loss_of),
                         find_unused_parameters=spec.variant == "radial" and len(data.lenses) > 1)
    where = ctx.record()

    def checkpoint():
        if ctx.main:
            save_checkpoint(ckpt_path, training_state(
                step=step, settings=settings, config_json=config.to_json(), data_key=key, model=model, ema=ema,
                opt=opt, rng=rng, history=history, seconds=prior_s + time.perf_counter() - t0))
        ctx.barrier()

    t0 = time.perf_counter()
    model.train()
    loss_v = float("nan")
    with open(run_dir / "log.jsonl" if ctx.main else os.devnull, "a", encoding="utf-8") as logf:
        while step < config.iters:
            groups = local_groups(data.sample(rng, config.batch).groups, rows)
            loss = step_loss(_groups_to_torch(Batch(groups), ctx.device))
            update(opt, loss, cosine_lr(config, step), model, ema, config.ema_decay)
            step += 1
            loss_v = ctx.mean(loss.detach())
            if ctx.main and config.validate_every and step % config.validate_every == 0 and step < config.iters:
                rec = {"step": step, "loss": loss_v, "seconds": prior_s + time.perf_counter() - t0,
                       "held_out_ema": evaluate(ema, data)["mean"], "held_out_model": evaluate(model, data)["mean"],
                       **where}
                history.append(rec)
                logf.write(json.dumps(rec) + "\n")
                logf.flush()
            after_step(step, config.iters, config.checkpoint_every, loss_v, checkpoint, progress, on_step)
    seconds = prior_s + time.perf_counter() - t0
    held = {}
    if ctx.main:
        held = {"ema": evaluate(ema, data), "model": evaluate(model, data)}
        rec = {"step": step, "loss": loss_v, "seconds": seconds, "held_out_ema": held["ema"]["mean"],
               "held_out_model": held["model"]["mean"], "final": True, **where}
        with open(run_dir / "log.jsonl", "a", encoding="utf-8") as logf:
            logf.write(json.dumps(rec) + "\n")
    return TrainResult(config, spec, model.cpu(), ema.cpu(), data, step, seconds, history, held, where)
