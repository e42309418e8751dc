"""Depth-network training config as data (like ``dacn_config``): every
field decides the weights except those in ``OPERATIONAL``."""
from __future__ import annotations

from dataclasses import dataclass, fields

from ...errors import InputRangeError
from .arch import DepthNetSpec
from ..common.config import JSONConfig

OPERATIONAL = ("data", "checkpoint_every")
INPUTS = ("capture", "target")


@dataclass(frozen=True)
class DepthTrainConfig(JSONConfig):
    data: str                                  # a folder of pre-built DA2T pairs (their captures and depths)
    widths: tuple = (12, 24, 48, 64)
    input: str = "capture"                     # the aberrated capture (what a user has) or the sharp target
    iters: int = 2000
    batch: int = 4
    crop: int = 128
    lr: float = 1e-3
    betas: tuple = (0.9, 0.99)
    ema_decay: float = 0.999
    augment: bool = True
    val_fraction: float = 0.1                  # the split by scene, when the data has none recorded
    test_fraction: float = 0.1
    split_seed: int = 0
    train_scenes: int = 0
    seed: int = 0
    threads: int = 1
    checkpoint_every: int = 500

    def __post_init__(self):
        object.__setattr__(self, "data", str(self.data))
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        if self.input not in INPUTS:
            raise InputRangeError("input", self.input, " or ".join(INPUTS))
        for name in ("iters", "batch", "crop", "threads", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise InputRangeError(name, getattr(self, name), ">= 1")
        if not self.lr > 0:
            raise InputRangeError("lr", self.lr, "> 0")
        if not (0.0 <= self.ema_decay < 1.0):
            raise InputRangeError("ema_decay", self.ema_decay, "[0, 1)")
        self.spec()

    def spec(self) -> DepthNetSpec:
        return DepthNetSpec(widths=self.widths)

    def lr_at(self, step: int) -> float:
        """Cosine from lr to lr / 100 over the run."""
        import math
        return self.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(step / self.iters, 1.0))))

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["widths"], d["betas"] = list(self.widths), list(self.betas)
        return d

    def result_settings(self) -> dict:
        return {k: v for k, v in self.as_dict().items() if k not in OPERATIONAL}
