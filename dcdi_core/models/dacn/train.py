"""The DACN's training (DA2T) on the shared loop (``common.loop``: seeded,
resumable bit for bit, atomic checkpoints, torchrun).

A run folder holds ``config.json``, ``split.json`` (the split by scene it
trained under: training pairs only from 'train' scenes, validation from
'val', 'test' never read), ``data.json`` (the pairs' folder, key and ids),
``checkpoint.pt`` (besides the loop's training state, ``kind`` 'dacn' and
the network's ``spec``, which export reads) and ``log.jsonl``. A checkpoint
resumes only with the same result settings and the same pairs, DA2T
settings and split.

Each step: ``batch`` random crops of ``crop`` px from the training pairs
(``data.PairCrops``: within the imaged area, flips and rotations, depth
encoded per crop as the spec says), the network's correction of the input
(the depth-aware capture, or the depth-unaware baseline), L1 against the
sharp target, Adam, the learning rate by its milestones
(``DACNTrainConfig.lr_at``), then the EMA. Validation: PSNR and SSIM on the
validation pairs' centre crops (``evaluate``). ``seconds`` is this session's
training time.

Under N processes each draws the same global batch of crops and trains on
its N-th; rank 0 alone writes the run folder (and the split, if the data has
none).
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...atomic import write_text
from ...errors import InputRangeError
from .. import require_torch
from ..common.loop import Network, train_network
from ..common.metrics import psnr, ssim
from ..common.split import Split, rank_key, split_by_scene
from ...errors import ModelError
from ..runtime.depth_encoding import encode_depth
from .config import DACNTrainConfig
from .data import PairCrops, finished_pairs, load_pair, pair_path

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


def extras_of(spec) -> tuple:
    """What a network of ``spec`` reads besides the input and depth (the
    order of its forward's arguments)."""
    return (("deconvolved",) if spec.refine else ()) + (("field",) if spec.condition else ())


def evaluate(model, data: DACNData, config: DACNTrainConfig, ids=None) -> dict:
    """PSNR / SSIM (``models.metrics``, data range 1, output clipped to [0, 1])
    of the network's correction and of its input, on the centre crops of the
    validation pairs (``ids``: others), mean over pairs; the crops' depth,
    deconvolution and field as inference prepares them (``correct``)."""
    from ..runtime.conditioning import field_maps
    from .correct import correct
    spec = model.spec
    ids = data.val if ids is None else ids
    if not ids:
        return {}
    records = finished_pairs(data.root)
    rows = []
    model.eval()
    for pid in ids:
        p = load_pair(pair_path(data.root, pid), records.get(pid))
        h, w = p.depth.shape
        s_h, s_w = min(config.val_size, h), min(config.val_size, w)
        r0, c0 = (h - s_h) // 2, (w - s_w) // 2
        x = centre_crop(getattr(p, config.input), config.val_size)
        y = centre_crop(p.target, config.val_size).transpose(2, 0, 1)
        dec = centre_crop(p.deconvolved, config.val_size) if spec.refine else None
        fm = None
        if spec.condition:
            centre, pitch, sd = p.geometry()
            fm = field_maps(centre, pitch, sd, np.arange(r0, r0 + s_h), np.arange(c0, c0 + s_w))
        out = correct(model, x, centre_crop(p.depth, config.val_size), deconvolved=dec, field=fm,
                      tile=max(s_h, s_w), overlap=0)
        out = np.clip(out, 0.0, 1.0).transpose(2, 0, 1)
        xin = np.clip(x.transpose(2, 0, 1), 0.0, 1.0)
        row = {"id": pid, "psnr": float(psnr(out, y, 1.0)), "psnr_input": float(psnr(xin, y, 1.0))}
        if min(y.shape[-2:]) >= 11:
            row["ssim"], row["ssim_input"] = float(ssim(out, y, 1.0)), float(ssim(xin, y, 1.0))
        rows.append(row)
    model.train()
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "id"}
    return {"mean": mean, "pairs": rows}


def srgb(x):
    """sRGB encoding of linear values in [0, 1] (torch; IEC 61966-2-1)."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def correction_loss(kind: str, out, y):
    """``DACNTrainConfig.loss`` of the network's output against the target."""
    if kind == "l1":
        return (out - y).abs().mean()
    inside = out.clamp(0.0, 1.0)
    return (srgb(inside) - srgb(y.clamp(0.0, 1.0))).abs().mean() + (out - inside).abs().mean()


class PairTraining(Network):
    """What a network trained on DA2T crops shares: the pairs and their split
    (``open_data``; recorded in the run folder as ``split.json``, and
    ``data.json``: the pairs' folder, key and ids), the crops, Adam, and the
    checkpoint's ``kind`` and ``spec``. A batch, by default: (input, target,
    encoded depth) tensors (B, C, crop, crop). Subclasses: ``stream``,
    ``kind``, ``encoding`` (of the crops' depth), ``build``, ``loss``,
    ``validate``, ``final``."""

    data_what = "data (pairs, their DA2T settings or the split)"
    kind = ""

    def open_data(self, run_dir, say) -> DACNData:
        return open_data(self.config)

    def data_key(self, data: DACNData) -> str:
        return data.key

    def write_records(self, run_dir, data: DACNData) -> None:
        data.split.save(run_dir / "split.json")
        write_text(run_dir / "data.json", json.dumps({"root": str(data.root), "key": data.key, "train": data.train,
                                                      "val": data.val}, indent=1) + "\n")

    def optimizer(self, model):
        return torch.optim.Adam(model.parameters(), lr=self.config.lr, betas=self.config.betas)

    def batches(self, data: DACNData):
        c = self.config
        crops = PairCrops([pair_path(data.root, p) for p in data.train], self.encoding, augment=c.augment,
                          records=finished_pairs(data.root), choose=getattr(c, "crop_choice", 1))
        extras = self.extras

        def draw(rng, rows, device):
            return self.tensors(crops.sample(rng, c.batch, c.crop, input=c.input, extras=extras), rows, device)
        return draw

    extras: tuple = ()

    def tensors(self, batch: tuple, rows: slice, device) -> tuple:
        """The loss's arguments from this rank's ``rows`` of the global batch
        of crops (input, target, encoded depth)."""
        return tuple(_tensor(a[rows]).to(device) for a in batch)

    def checkpoint_extra(self) -> dict:
        return {"kind": self.kind, "spec": json.dumps(self.config.spec().as_dict())}


class DACNTraining(PairTraining):
    """The DACN's part of the shared loop."""

    stream = 13
    kind = "dacn"

    @property
    def encoding(self) -> str:
        return self.config.spec().depth_encoding

    @property
    def extras(self) -> tuple:
        return extras_of(self.config.spec())

    def build(self, data: DACNData):
        return DACN(self.config.spec())

    def loss(self, model, x, y, d, *extras):
        return correction_loss(self.config.loss, model(x, d, **dict(zip(self.extras, extras))), y)

    def validate(self, model, ema, data: DACNData) -> dict:
        return {"val_ema": evaluate(ema, data, self.config).get("mean")}

    def final(self, model, ema, data: DACNData) -> tuple[dict, dict]:
        val = {"ema": evaluate(ema, data, self.config), "model": evaluate(model, data, self.config)}
        return val, {"val_ema": val["ema"].get("mean"), "val_model": val["model"].get("mean")}


def train_dacn(config: DACNTrainConfig, run_dir, *, progress=None, on_step=None, log=None,
               device: str = "cpu") -> DACNResult:
    """Train (or resume) the run in ``run_dir`` (``common.loop.train_network``:
    callbacks, device, torchrun)."""
    r = train_network(DACNTraining(config), run_dir, device=device, progress=progress, on_step=on_step, log=log)
    return DACNResult(config, r.model, r.ema, r.data, r.step, r.seconds, r.history, r.validation, r.where)
