"""The Omni-Lens-Field's training config (data as a nested config)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

from ...errors import InputRangeError
from ..common.config import OPERATIONAL, JSONConfig
from .data import PSFDataConfig
from .spec import SIZES, VARIANTS


@dataclass(frozen=True)
class OLFTrainConfig(JSONConfig):
    """An Omni-Lens-Field training run. Defaults: the paper's released
    settings (AdamW lr 1e-4, betas (0.9, 0.99), weight decay 0; cosine to
    1e-7; MSE; EMA 0.999; batch 256)."""

    data: PSFDataConfig
    size: str = "tiny"
    hidden_layers: int | None = None    # override the size's N
    width: int | None = None            # override the size's W
    iters: int = 1000
    batch: int = 256
    lr: float = 1e-4
    lr_min: float = 1e-7
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.0
    ema_decay: float = 0.999
    seed: int = 0
    threads: int = 1                    # torch threads (the same count gives the same bits)
    checkpoint_every: int = 500
    validate_every: int = 0             # 0: at the end only

    def __post_init__(self):
        if isinstance(self.data, dict):
            object.__setattr__(self, "data", PSFDataConfig.from_dict(self.data))
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        if self.size not in SIZES:
            raise InputRangeError("size", self.size, ", ".join(SIZES))
        for name in ("iters", "batch", "threads", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise InputRangeError(name, getattr(self, name), ">= 1")
        if self.validate_every < 0:
            raise InputRangeError("validate_every", self.validate_every, ">= 0 (0: at the end only)")
        if not (0 < self.lr and 0 <= self.lr_min <= self.lr):
            raise InputRangeError("lr, lr_min", (self.lr, self.lr_min), "0 <= lr_min <= lr, lr > 0")
        if not (0.0 <= self.ema_decay < 1.0):
            raise InputRangeError("ema_decay", self.ema_decay, "[0, 1)")
        if self.data.variant not in VARIANTS:
            raise InputRangeError("variant", self.data.variant, " or ".join(VARIANTS))

    @property
    def variant(self) -> str:
        return self.data.variant

    def lr_at(self, step: int) -> float:
        """Learning rate of update ``step`` (0-based): cosine from lr to lr_min over ``iters``."""
        t = min(step, self.iters) / self.iters
        return self.lr_min + (self.lr - self.lr_min) * 0.5 * (1.0 + math.cos(math.pi * t))

    def arch(self) -> dict:
        """hidden_layers and width after the size and its overrides."""
        n, w = SIZES[self.size]
        return {"hidden_layers": self.hidden_layers if self.hidden_layers is not None else n,
                "width": self.width if self.width is not None else w}

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["data"] = self.data.as_dict()
        d["betas"] = list(self.betas)
        return d

    def result_settings(self) -> dict:
        """The flattened settings that decide the weights (data.* included)."""
        d = self.as_dict()
        out = {k: v for k, v in d.items() if k not in OPERATIONAL and k != "data"}
        out.update({f"data.{k}": v for k, v in d["data"].items()})
        return out
