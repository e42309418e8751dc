"""A small monocular metric-depth network for the minimalist lens's captures.

The minimalist lens's PSF changes with depth, so its aberrations carry
depth as well as the picture's content does: the network sees the
aberrated capture (linear RGB in [0, 1]) and predicts the scene's inverse
depth on the ``data.depth`` 'diopter' scale (0.7 m / depth: 1 at 0.7 m, 0 at
infinity), bounded to [0, 7] (0.1 m) by a sigmoid. A U-Net: ``len(widths)``
levels of two 3x3 conv + GELU, stride-2 downsampling, bilinear upsampling
with skips; inputs of any size are padded (replicate) to a multiple of
2^(levels - 1) and cropped back.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from .. import require_torch
from ..data.depth import DIOPTER_SCALE_M, NEAR_M

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

MAX_DIOPTER = DIOPTER_SCALE_M / NEAR_M


@dataclass(frozen=True)
class DepthNetSpec:
    widths: tuple = (12, 24, 48, 64)

    def __post_init__(self):
        from ...optics.errors import InputRangeError
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

    def forward(self, x):
        """(B, 3, H, W) capture in [0, 1] -> (B, 1, H, W) diopters in [0, 7]."""
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
        out = MAX_DIOPTER * torch.sigmoid(self.head(x))
        return out[..., :h, :w]


def diopters_to_metres(p, floor: float = 1e-4):
    """Metric depth (m) of the diopter scale: 0.7 m / p, with p floored
    (``floor`` = 7 km) so that a prediction of 'infinity' stays finite."""
    import numpy as np
    return DIOPTER_SCALE_M / np.maximum(np.asarray(p, dtype=np.float64), floor)


__all__ = ["DepthNet", "DepthNetSpec", "diopters_to_metres", "MAX_DIOPTER"]
