"""Training the depth network (``arch.DepthNet``) on DA2T pairs, on the
shared loop (``common.loop``: seeded, atomic checkpoints, resumable bit for
bit): the capture in, the depth on the sensor out, L1 of log depth (a
relative error, the same weight for every distance; depths clamped to
[0.1, 80] m, the sky at 80 m), Adam with a cosine schedule
(``DepthTrainConfig.lr_at``), EMA. The pairs, their split by scene (test
scenes never read), the run folder's records and the checkpoint's ``kind``
and ``spec`` as the DACN's (``dacn.train.PairTraining``). Validation, at the
end: AbsRel, RMSE (m) and delta1 of the EMA on the validation pairs' centre
256 px. ``seconds`` is this session's training time.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import require_torch
from ..common.loop import train_network
from ..common.metrics import depth_scores
from ..dacn.data import load_pair, pair_path
from ..dacn.train import PairTraining, centre_crop
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


class DepthTraining(PairTraining):
    """The depth network's part of the shared loop: the crops' depth comes
    diopter-encoded (0.7 m / depth; 0: infinity or not imaged) and is turned
    back into metres for the loss."""

    stream = 17
    kind = "depth"
    encoding = "diopter"
    validate_every = 0                  # validated once, at the end

    def build(self, data):
        return DepthNet(self.config.spec())

    def tensors(self, batch: tuple, rows: slice, device) -> tuple:
        # (image, encoded depth) in the crops' own memory layout, not made
        # contiguous: the convolutions' last bits depend on it, and runs
        # resumed from earlier checkpoints must end bit for bit as they would have
        x, _, d = batch
        return torch.from_numpy(np.clip(x[rows], 0, 1)).to(device), torch.from_numpy(d[rows]).to(device)

    def loss(self, model, x, d):
        metres = DIOPTER_SCALE_M / d.clamp(min=1e-6)
        return (model(x) - log_target(metres)).abs().mean()

    def final(self, model, ema, data) -> tuple[dict, dict]:
        ema.eval()
        val = evaluate_depth(ema, data.root, data.val, input=self.config.input, size=256)
        return val, {"val_ema": val}


def train_depth(config: DepthTrainConfig, run_dir, *, progress=None, on_step=None, log=None) -> DepthResult:
    """Train (or resume) the run in ``run_dir`` (``common.loop.train_network``:
    the callbacks), on the CPU, in this process alone."""
    r = train_network(DepthTraining(config), run_dir, distributed=False, progress=progress, on_step=on_step,
                      log=log)
    return DepthResult(config, r.model, r.ema, r.step, r.seconds, r.validation)
