"""The training of the Omni-Lens-Field, on the shared loop
(``common.loop``: seeded, resumable bit for bit, atomic checkpoints,
torchrun).

One run lives in a folder: ``config.json`` (the settings), ``points.npz``
(the traced off-grid and held-out PSFs, so a resumed run need not trace them
again), ``checkpoint.pt`` (every ``checkpoint_every`` iterations and at the
end; besides the loop's training state, ``seconds``: the training time of
all sessions so far) and ``log.jsonl``. A checkpoint resumes only with the
same result settings and the same lenses' optics and PSF algorithm.

Each step: a batch from ``OLFData.sample`` (lenses uniform; grid and
off-grid points), the network's PSFs, MSE on the paper's scale (prediction
and target divided by the target's per-channel peak), AdamW, learning rate
cosine from ``lr`` to ``lr_min`` over ``iters`` (``OLFTrainConfig.lr_at``),
then the EMA of the weights. Validation: ``metrics.psf_scores`` on the
held-out points, of the EMA and of the model.

Under N processes each draws the same global batch and trains on its N-th
(``local_groups``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import require_torch
from ..common.loop import Network, train_network
from ..common.metrics import psf_scores
from .config import OLFTrainConfig
from .data import Batch, OLFData, build_data, data_key

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


class OLFTraining(Network):
    """The OLF's part of the shared loop."""

    stream = 7
    data_what = "data (a lens's optics or the PSF algorithm)"
    # the exported file records the training time of the whole run as its cost
    session_seconds = False

    def __init__(self, config: OLFTrainConfig, *, cache_dir=None, lenses: dict | None = None):
        super().__init__(config)
        self.cache_dir, self.lenses = cache_dir, lenses

    def open_data(self, run_dir, say) -> OLFData:
        # rank 0 traces and caches the PSFs, the others read them
        return build_data(self.config.data, cache_dir=self.cache_dir, points_file=run_dir / "points.npz",
                          lenses=self.lenses, log=say)

    def data_key(self, data: OLFData) -> str:
        return data_key(self.config.data, [ls.lens for ls in data.lenses])

    def build(self, data: OLFData):
        model = OLF(data.spec(**self.config.arch()))
        _init_heads_from_data(model, data)
        return model

    def optimizer(self, model):
        c = self.config
        return torch.optim.AdamW(model.parameters(), lr=c.lr, betas=c.betas, weight_decay=c.weight_decay)

    def batches(self, data: OLFData):
        def draw(rng, rows, device):
            groups = local_groups(data.sample(rng, self.config.batch).groups, rows)
            return (_groups_to_torch(Batch(groups), device),)
        return draw

    def loss(self, model, groups):
        return loss_of(model, groups)

    def unused_parameters(self, data: OLFData) -> bool:
        # radial, several lenses: a rank's share may lack a lens, whose head is then unused there
        return self.config.data.variant == "radial" and len(data.lenses) > 1

    def final(self, model, ema, data: OLFData) -> tuple[dict, dict]:
        held = {"ema": evaluate(ema, data), "model": evaluate(model, data)}
        return held, {"held_out_ema": held["ema"]["mean"], "held_out_model": held["model"]["mean"]}


def train(config: OLFTrainConfig, run_dir, *, cache_dir=None, lenses: dict | None = None, progress=None,
          on_step=None, log=None, device: str = "cpu") -> TrainResult:
    """Train (or resume) the run in ``run_dir`` (``common.loop.train_network``:
    callbacks, device, torchrun). ``cache_dir``: the PSF library cache (None:
    the default; False: none); ``lenses``: {id: Lens} instead of loading them."""
    net = OLFTraining(config, cache_dir=cache_dir, lenses=lenses)
    r = train_network(net, run_dir, device=device, progress=progress, on_step=on_step, log=log)
    return TrainResult(config, r.model.spec, r.model, r.ema, r.data, r.step, r.seconds, r.history, r.validation,
                       r.where)
