"""A small monocular metric-depth network for the minimalist lens's captures.

The minimalist lens's PSF changes with depth, so its aberrations carry
depth as well as the picture's content does: the network sees the
aberrated capture (linear RGB in [0, 1]) and predicts the natural log of the
metric depth, clamped to [log 0.1 m, log 1000 m], starting from 2 m (the
last layer's bias; its weights start at zero, so that no unit starts
saturated). A bounded sigmoid head on inverse depth, tried first, collapsed
to 'everything at infinity' within a few hundred steps: its gradient
vanishes where the sigmoid saturates. A U-Net: ``len(widths)``
levels of two 3x3 conv + GELU, stride-2 downsampling, bilinear upsampling
with skips; inputs of any size are padded (replicate) to a multiple of
2^(levels - 1) and cropped back.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import math

from .. import require_torch

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

LOG_NEAR, LOG_FAR, LOG_START = math.log(0.1), math.log(1000.0), math.log(2.0)


@dataclass(frozen=True)
class DepthNetSpec:
    widths: tuple = (12, 24, 48, 64)

    def __post_init__(self):
        from ...errors import InputRangeError
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        if len(self.widths) < 2 or min(self.widths) < 1:
            raise InputRangeError("depth network widths", self.widths, "two or more levels of >= 1 channels")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d


def _block(c_in, c_out):
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.GELU(),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.GELU())


class DepthNet(nn.Module):
    def __init__(self, spec: DepthNetSpec = DepthNetSpec()):
        super().__init__()
        self.spec = spec
        w = spec.widths
        self.enc = nn.ModuleList([_block(3, w[0])] + [_block(w[i - 1], w[i]) for i in range(1, len(w))])
        self.down = nn.ModuleList([nn.Conv2d(w[i], w[i], 3, stride=2, padding=1) for i in range(len(w) - 1)])
        self.dec = nn.ModuleList([_block(w[i + 1] + w[i], w[i]) for i in range(len(w) - 1)])
        self.head = nn.Conv2d(w[0], 1, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.constant_(self.head.bias, LOG_START)

    def forward(self, x):
        """(B, 3, H, W) capture in [0, 1] -> (B, 1, H, W) log depth (log metres)."""
        h, w = x.shape[-2:]
        m = 2 ** (len(self.enc) - 1)
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        skips = []
        for i, enc in enumerate(self.enc):
            x = enc(x)
            if i < len(self.down):
                skips.append(x)
                x = self.down[i](x)
        for i in reversed(range(len(self.dec))):
            x = F.interpolate(x, size=skips[i].shape[-2:], mode="bilinear", align_corners=False)
            x = self.dec[i](torch.cat([x, skips[i]], dim=1))
        out = self.head(x).clamp(LOG_NEAR, LOG_FAR)
        return out[..., :h, :w]


def log_target(depth_m, far_m: float = 80.0):
    """The training target of metric depths (torch or numpy): log of the
    depth clamped to [0.1 m, ``far_m``] (infinity, the sky, is ``far_m``)."""
    if isinstance(depth_m, torch.Tensor):
        return depth_m.clamp(0.1, far_m).log()
    import numpy as np
    return np.log(np.clip(depth_m, 0.1, far_m))


__all__ = ["DepthNet", "DepthNetSpec", "log_target"]
