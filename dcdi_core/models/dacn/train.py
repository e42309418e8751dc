"""The DACN training loop (DA2T): plain, seeded, resumable, like the OLF's.

A run folder holds ``config.json``, ``split.json`` (the split by scene it
trained under: training pairs only from 'train' scenes, validation from
'val', 'test' never read), ``checkpoint.pt`` (atomic, every
``checkpoint_every`` iterations and at the end: weights, EMA, optimiser,
iteration, the crop generator's and torch's RNG states) and ``log.jsonl``.
Same config, data and thread count: the same weights, bit for bit; a
killed run started again resumes from its last checkpoint and ends where an
uninterrupted run would. A checkpoint written with other settings or other
data is refused, naming them.

Each step: ``batch`` random crops of ``crop`` px from the training pairs
(``data.da2t.PairCrops``: within the imaged area, flips and rotations,
depth encoded per crop as the spec says), the network's correction of the
input (the depth-aware capture, or the depth-unaware baseline), L1 against
the sharp target, Adam, the learning rate by its milestones, then the EMA.

``device`` (auto, cpu, cuda[:N]) and the number of processes (``torchrun
--nproc-per-node N``, ``distributed``) are not settings: a checkpoint resumes
on another device or world size. Under N processes each draws the same
global batch of crops and trains on its N-th; rank 0 alone writes the run
folder (and the split, if the data has none). The log records the device and
world size.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...atomic import write_text
from .. import require_torch
from .data import PairCrops, finished_pairs, load_pair, pair_path
from ..runtime.depth_encoding import encode_depth
from ...errors import InputRangeError
from ..common.split import Split, rank_key, split_by_scene
from ..errors import ModelError
from ..common.metrics import psnr, ssim
from ..common.checkpoint import after_step, check_data, make_ema, open_run, restore, save_checkpoint, training_state, update
from .config import DACNTrainConfig
from ..common.distributed import Context, LossModule

torch = require_torch()
from .arch import DACN  # noqa: E402  (after the torch check)


@dataclass
class DACNData:
    root: Path
    split: Split
    train: list                 # pair ids
    val: list
    key: str                    # what the pairs hold: DA2T settings, pair ids, split


@dataclass
class DACNResult:
    config: DACNTrainConfig
    model: object
    ema: object
    data: DACNData
    step: int
    seconds: float
    history: list = field(default_factory=list)
    validation: dict = field(default_factory=dict)     # rank 0 only
    where: dict = field(default_factory=dict)          # device and world size it ran on


def open_data(config: DACNTrainConfig) -> DACNData:
    """The pre-built pairs of ``config.data`` and their split by scene: the
    recorded ``split.json`` there, else one made now (seeded) and recorded."""
    root = Path(config.data)
    pairs = finished_pairs(root)
    if not pairs:
        raise ModelError(f"{root}: no DA2T pairs (pairs.jsonl); build them first: dcdi dacn pairs SOURCE -o {root}")
    frames = {rec["frame"]: rec["scene"] for rec in pairs.values()}
    sp_path = root / "split.json"
    if sp_path.exists():
        split = Split.load(sp_path)
        missing = sorted(set(frames) - set(split.ids))
        if missing:
            raise ModelError(f"{sp_path}: frames not in the recorded split ({', '.join(missing[:5])}...); "
                             "remove it to split afresh (the test scenes may change)")
    else:
        split = split_by_scene(frames, val=config.val_fraction, test=config.test_fraction, seed=config.split_seed)
        split.save(sp_path)
    part = {pid: split.part(rec["frame"]) for pid, rec in pairs.items()}
    train = sorted(p for p, q in part.items() if q == "train")
    if config.train_scenes:
        train = _fewer_scenes(train, pairs, split, config)
    val = sorted(p for p, q in part.items() if q == "val")
    if not train:
        raise ModelError(f"{root}: no training pairs after the split by scene ({len(split.scenes)} scenes)")
    da2t = (root / "da2t.json").read_text(encoding="utf-8") if (root / "da2t.json").exists() else ""
    h = hashlib.sha256(json.dumps([json.loads(da2t) if da2t else None, train, val, split.as_dict()["scenes"]],
                                  sort_keys=True).encode()).hexdigest()
    return DACNData(root, split, train, val, h)


def _fewer_scenes(train: list, pairs: dict, split: Split, config: DACNTrainConfig) -> list:
    """The training pairs of ``config.train_scenes`` of the training scenes,
    ranked by a seeded hash (nested: n scenes are among the first n + 1)."""
    scenes = sorted({pairs[p]["scene"] for p in train}, key=lambda s: rank_key(config.split_seed + 1, s))
    if config.train_scenes > len(scenes):
        raise InputRangeError("train_scenes", config.train_scenes, f"<= {len(scenes)}, the training scenes "
                              f"of {config.data}")
    keep = set(scenes[:config.train_scenes])
    return [p for p in train if pairs[p]["scene"] in keep]


def _tensor(a):
    return torch.from_numpy(np.ascontiguousarray(a))


def centre_crop(a, size: int):
    h, w = a.shape[:2]
    s_h, s_w = min(size, h), min(size, w)
    r, c = (h - s_h) // 2, (w - s_w) // 2
    return a[r:r + s_h, c:c + s_w]


def evaluate(model, data: DACNData, config: DACNTrainConfig, ids=None) -> dict:
    """PSNR / SSIM (``models.metrics``, data range 1, output clipped to [0, 1])
    of the network's correction and of its input, on the centre crops of the
    validation pairs (``ids``: others), mean over pairs."""
    spec = model.spec
    ids = data.val if ids is None else ids
    if not ids:
        return {}
    rows = []
    device = next(model.parameters()).device
    model.eval()
    with torch.no_grad():
        for pid in ids:
            p = load_pair(pair_path(data.root, pid))
            x = centre_crop(getattr(p, config.input), config.val_size)
            y = centre_crop(p.target, config.val_size).transpose(2, 0, 1)
            d = encode_depth(centre_crop(p.depth, config.val_size), spec.depth_encoding)
            out = model(_tensor(x.transpose(2, 0, 1))[None].to(device),
                        _tensor(d)[None, None].to(device))[0].cpu().numpy()
            out = np.clip(out, 0.0, 1.0)
            xin = np.clip(x.transpose(2, 0, 1), 0.0, 1.0)
            row = {"id": pid, "psnr": float(psnr(out, y, 1.0)), "psnr_input": float(psnr(xin, y, 1.0))}
            if min(y.shape[-2:]) >= 11:
                row["ssim"], row["ssim_input"] = float(ssim(out, y, 1.0)), float(ssim(xin, y, 1.0))
            rows.append(row)
    model.train()
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "id"}
    return {"mean": mean, "pairs": rows}


def l1_loss(model, x, y, d):
    """Mean absolute difference of the network's correction of ``x`` from ``y``."""
    return (model(x, d) - y).abs().mean()


def train_dacn(config: DACNTrainConfig, run_dir, *, progress=None, on_step=None, log=None,
               device: str = "cpu") -> DACNResult:
    """Train (or resume) the run in ``run_dir``. ``progress(step, iters,
    loss)`` after each step; ``on_step(step)`` too (an exception there stops
    the run as a kill would, after the step and before any later checkpoint).
    ``device``: auto, cpu, cuda or cuda:N (``distributed.resolve_device``);
    under torchrun the processes share each global batch (module docstring)."""
    ctx = Context.from_environment(device)
    try:
        result = _train_dacn(config, run_dir, ctx, progress=progress, on_step=on_step, log=log)
    except BaseException:
        ctx.close(clean=False)
        raise
    ctx.close()
    return result


def _train_dacn(config: DACNTrainConfig, run_dir, ctx: Context, *, progress, on_step, log) -> DACNResult:
    say = (log or (lambda s: None)) if ctx.main else (lambda s: None)
    progress = progress if ctx.main else None
    rows = ctx.part(config.batch)                        # refused before any work
    run_dir, ckpt_path, settings, ck = open_run(run_dir, config)
    with ctx.main_first():                               # rank 0 records the split if there is none
        data = open_data(config)
    check_data(ck, ckpt_path, data.key, "data (pairs, their DA2T settings or the split)")
    if ctx.main:
        write_text(run_dir / "config.json", config.to_json() + "\n")
        data.split.save(run_dir / "split.json")
        write_text(run_dir / "data.json", json.dumps({"root": str(data.root), "key": data.key, "train": data.train,
                                                      "val": data.val}, indent=1) + "\n")
    spec = config.spec()
    torch.manual_seed(config.seed)
    model = DACN(spec).to(ctx.device)
    ema = make_ema(model)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, betas=config.betas)
    rng = np.random.default_rng([config.seed, 13])
    crops = PairCrops([pair_path(data.root, p) for p in data.train], spec.depth_encoding, augment=config.augment)
    step, history = restore(ck, model, ema, opt, rng, say=say, path=ckpt_path, iters=config.iters)
    step_loss = ctx.wrap(LossModule(model, l1_loss))
    where = ctx.record()

    def checkpoint():
        if ctx.main:
            save_checkpoint(ckpt_path, training_state(
                step=step, settings=settings, config_json=config.to_json(), data_key=data.key, model=model,
                ema=ema, opt=opt, rng=rng, history=history, kind="dacn", spec=json.dumps(spec.as_dict())))
        ctx.barrier()

    t0 = time.perf_counter()
    model.train()
    loss_v = float("nan")
    with open(run_dir / "log.jsonl" if ctx.main else os.devnull, "a", encoding="utf-8") as logf:
        while step < config.iters:
            batch = crops.sample(rng, config.batch, config.crop, input=config.input)   # the global batch
            x, y, d = (_tensor(a[rows]).to(ctx.device) for a in batch)                # this rank's share
            loss = step_loss(x, y, d)
            update(opt, loss, config.lr_at(step), model, ema, config.ema_decay)
            step += 1
            loss_v = ctx.mean(loss.detach())
            if ctx.main and config.validate_every and step % config.validate_every == 0 and step < config.iters:
                rec = {"step": step, "loss": loss_v, "seconds": time.perf_counter() - t0,
                       "it_per_s": step / max(time.perf_counter() - t0, 1e-9),
                       "val_ema": evaluate(ema, data, config).get("mean"), **where}
                history.append(rec)
                logf.write(json.dumps(rec) + "\n")
                logf.flush()
                say(f"iteration {step}: loss {loss_v:.4g}, validation {rec['val_ema']}")
            after_step(step, config.iters, config.checkpoint_every, loss_v, checkpoint, progress, on_step)
    seconds = time.perf_counter() - t0
    val = {}
    if ctx.main:
        val = {"ema": evaluate(ema, data, config), "model": evaluate(model, data, config)}
        rec = {"step": step, "loss": loss_v, "seconds": seconds, "val_ema": val["ema"].get("mean"),
               "val_model": val["model"].get("mean"), "final": True, **where}
        with open(run_dir / "log.jsonl", "a", encoding="utf-8") as logf:
            logf.write(json.dumps(rec) + "\n")
    return DACNResult(config, model.cpu(), ema.cpu(), data, step, seconds, history, val, where)
