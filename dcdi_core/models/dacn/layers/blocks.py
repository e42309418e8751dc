"""EDSR residual blocks (Lim et al. 2017): conv 3 x 3, ReLU, conv 3 x 3, the
result scaled and added to the input (no batch norm)."""
from __future__ import annotations

from ... import require_torch

torch = require_torch()
nn = torch.nn


class ResBlock(nn.Module):
    def __init__(self, channels: int, res_scale: float = 1.0):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.act = nn.ReLU()
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.res_scale = res_scale

    def forward(self, x):
        return x + self.res_scale * self.conv2(self.act(self.conv1(x)))
