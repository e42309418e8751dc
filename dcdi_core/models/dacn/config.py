"""DACN training configs as data (frozen dataclass, JSON round-trip), like
the OLF's (``config``): every field decides the weights except those in
``OPERATIONAL``. Defaults: the paper's released settings (Adam 2e-4, betas
(0.9, 0.99), L1, EMA 0.999, the learning rate halved at 50, 80, 90 and 95 %
of the iterations (the release's 100k, 160k, 180k, 190k of 200k), flips and
rotations) at this machine's scale (batch 4 of 128^2 instead of 8 of
256^2)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from ...errors import InputRangeError
from .spec import CONFIGS, DACNSpec, named
from ..common.config import JSONConfig

# data: where the pre-built pairs are (they may move; what they hold is keyed)
OPERATIONAL = ("data", "checkpoint_every", "validate_every")
INPUTS = ("capture", "baseline")
SCHEDULES = ("cosine", "steps")
LOSSES = ("srgb_l1", "l1")
# what configs written before these settings existed trained with
BEFORE = {"schedule": "steps", "warmup": 0.0, "loss": "l1", "crop_choice": 1}


@dataclass(frozen=True)
class DACNTrainConfig(JSONConfig):
    data: str                                  # a folder of pre-built DA2T pairs (models.dacn.data)
    config: str = "tiny"                       # a named DACN configuration
    arch: dict = field(default_factory=dict)   # DACNSpec fields replaced (switches, sizes, depth_encoding)
    input: str = "capture"                     # capture (DA2T) or baseline (the depth-unaware set)
    iters: int = 1000
    batch: int = 4
    crop: int = 128
    lr: float = 2e-4
    betas: tuple = (0.9, 0.99)
    # cosine: a linear warm-up over the first ``warmup`` of the iterations, then a cosine from lr down to
    # lr / 100; steps: the learning rate times gamma at each milestone (the paper's release)
    schedule: str = "cosine"
    warmup: float = 0.03
    milestones: tuple = (0.5, 0.8, 0.9, 0.95)  # fractions of iters where the learning rate is multiplied by gamma
    gamma: float = 0.5
    # srgb_l1: L1 of the sRGB-encoded images (errors weighted as a viewer sees them: the linear L1 lets the
    # bright pixels dominate and leaves the shadows' noise) plus the linear excess outside [0, 1]; l1: linear
    loss: str = "srgb_l1"
    crop_choice: int = 2                       # a crop's place: the worst captured of this many (data.PairCrops)
    ema_decay: float = 0.999
    augment: bool = True
    val_fraction: float = 0.1                  # the split by scene, if the data has none recorded
    test_fraction: float = 0.1
    split_seed: int = 0
    train_scenes: int = 0                      # > 0: train on this many of the training scenes (a data-size curve)
    val_size: int = 256                        # validation: the centre crop of each validation pair
    seed: int = 0
    threads: int = 1                           # torch threads (the same count gives the same bits)
    checkpoint_every: int = 500
    validate_every: int = 0                    # 0: at the end only

    def __post_init__(self):
        object.__setattr__(self, "data", str(self.data))
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        object.__setattr__(self, "milestones", tuple(float(m) for m in self.milestones))
        object.__setattr__(self, "arch", dict(self.arch))
        if self.config not in CONFIGS:
            raise InputRangeError("config", self.config, ", ".join(CONFIGS))
        if self.input not in INPUTS:
            raise InputRangeError("input", self.input, " or ".join(INPUTS))
        if self.schedule not in SCHEDULES:
            raise InputRangeError("schedule", self.schedule, " or ".join(SCHEDULES))
        if self.loss not in LOSSES:
            raise InputRangeError("loss", self.loss, " or ".join(LOSSES))
        if not 0.0 <= self.warmup < 1.0:
            raise InputRangeError("warmup", self.warmup, "[0, 1) of the iterations")
        if self.crop_choice < 1:
            raise InputRangeError("crop_choice", self.crop_choice, ">= 1 (1: uniform places)")
        if self.train_scenes < 0:
            raise InputRangeError("train_scenes", self.train_scenes, ">= 0 (0: all training scenes)")
        for name in ("iters", "batch", "crop", "threads", "checkpoint_every", "val_size"):
            if getattr(self, name) < 1:
                raise InputRangeError(name, getattr(self, name), ">= 1")
        if self.validate_every < 0:
            raise InputRangeError("validate_every", self.validate_every, ">= 0 (0: at the end only)")
        if not self.lr > 0 or not 0 < self.gamma <= 1 or not all(0 < m < 1 for m in self.milestones):
            raise InputRangeError("lr, gamma, milestones", (self.lr, self.gamma, self.milestones),
                                  "lr > 0, 0 < gamma <= 1, milestones in (0, 1)")
        if not (0.0 <= self.ema_decay < 1.0):
            raise InputRangeError("ema_decay", self.ema_decay, "[0, 1)")
        self.spec()                            # the overrides must make a valid network

    def spec(self) -> DACNSpec:
        return named(self.config, **self.arch)

    @classmethod
    def from_dict(cls, d: dict) -> "DACNTrainConfig":
        return cls(**{**BEFORE, **d})

    def lr_at(self, step: int) -> float:
        """Learning rate of update ``step`` (0-based)."""
        if self.schedule == "cosine":
            warm = round(self.warmup * self.iters)
            if step < warm:
                return self.lr * (step + 1) / warm
            t = (step - warm) / max(1, self.iters - warm)
            return self.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * min(t, 1.0))))
        k = sum(step >= round(m * self.iters) for m in self.milestones)
        return self.lr * self.gamma ** k

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["betas"], d["milestones"] = list(self.betas), list(self.milestones)
        return d

    def result_settings(self) -> dict:
        """The settings that decide the weights (the spec after overrides included)."""
        out = {k: v for k, v in self.as_dict().items() if k not in OPERATIONAL}
        out.update({f"spec.{k}": v for k, v in self.spec().as_dict().items()})
        return out

