"""Modulated deformable 3 x 3 convolution (DCNv2, Zhu et al. 2019) in plain torch.

torchvision's ``deform_conv2d`` does not load beside this torch, so the
operator is written here with one ``grid_sample``: the nine taps of every
output pixel are sampled at once (bilinear, zero outside the input, as DCN
does), multiplied by their masks and contracted with the weights by one
matmul over channels x taps (the einsum "nckhw,ock->nohw" without copies).

Conventions (torchvision's): stride 1, padding 1, dilation 1, one offset
group. ``offset`` is (N, 18, H, W): for tap k = 3 i + j (row i, column j of
the 3 x 3 kernel) channel 2k is the row offset dy and 2k + 1 the column
offset dx, in pixels; tap k of output pixel (h, w) reads the input at
(h + i - 1 + dy, w + j - 1 + dx). ``mask`` is (N, 9, H, W), one factor per
tap (the modulation; 1 everywhere and zero offsets is ``F.conv2d`` with
padding 1).
"""
from __future__ import annotations

import math

from ... import require_torch

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

TAPS = 9


def _base_grid(h: int, w: int, dtype, device):
    """(9, H, W) row and column positions of the nine taps at zero offset."""
    ki, kj = torch.meshgrid(torch.arange(3, device=device, dtype=dtype) - 1,
                            torch.arange(3, device=device, dtype=dtype) - 1, indexing="ij")
    rows = torch.arange(h, device=device, dtype=dtype).view(1, h, 1) + ki.reshape(TAPS, 1, 1)
    cols = torch.arange(w, device=device, dtype=dtype).view(1, 1, w) + kj.reshape(TAPS, 1, 1)
    return rows.expand(TAPS, h, w), cols.expand(TAPS, h, w)


def sample_taps(x, offset):
    """The nine bilinearly sampled taps of every output pixel: (N, C, 9, H, W)."""
    n, c, h, w = x.shape
    if offset.shape != (n, 2 * TAPS, h, w):
        raise ValueError(f"offset shape {tuple(offset.shape)}, expected {(n, 2 * TAPS, h, w)}")
    rows, cols = _base_grid(h, w, x.dtype, x.device)
    off = offset.view(n, TAPS, 2, h, w)
    py = rows + off[:, :, 0]                     # (N, 9, H, W) pixel coordinates
    px = cols + off[:, :, 1]
    # grid_sample's align_corners=False: pixel p sits at (2 p + 1) / size - 1
    grid = torch.stack(((2 * px + 1) / w - 1, (2 * py + 1) / h - 1), dim=-1)   # (N, 9, H, W, 2)
    taps = F.grid_sample(x, grid.view(n, TAPS * h, w, 2), mode="bilinear", padding_mode="zeros",
                         align_corners=False)
    return taps.view(n, c, TAPS, h, w)


def modulated_deform_conv3x3(x, offset, mask, weight, bias=None):
    """DCNv2 3 x 3 (stride 1, padding 1): x (N, C, H, W), offset (N, 18, H, W),
    mask (N, 9, H, W), weight (O, C, 3, 3), bias (O,) or None -> (N, O, H, W)."""
    n, c, h, w = x.shape
    if weight.shape[1:] != (c, 3, 3):
        raise ValueError(f"weight shape {tuple(weight.shape)}, expected (O, {c}, 3, 3)")
    if mask.shape != (n, TAPS, h, w):
        raise ValueError(f"mask shape {tuple(mask.shape)}, expected {(n, TAPS, h, w)}")
    cols = sample_taps(x, offset) * mask.unsqueeze(1)               # (N, C, 9, H, W)
    # the einsum "nckhw,ock->nohw" as one matmul over (c, k), no copies
    out = torch.matmul(weight.reshape(weight.shape[0], c * TAPS), cols.view(n, c * TAPS, h * w))
    out = out.view(n, -1, h, w)
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1)
    return out


class ModulatedDeformConv3x3(nn.Module):
    """DCNv2 3 x 3 whose offsets and masks come from a guide feature map:
    ``forward(x, guide)``. A 3 x 3 conv on ``guide`` (initialised to zero,
    so training starts from a plain convolution with masks 0.5) gives 18
    offset channels and 9 mask logits (through a sigmoid)."""

    def __init__(self, in_channels: int, out_channels: int, guide_channels: int | None = None, bias: bool = True):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels, 3, 3))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.conv_offset = nn.Conv2d(guide_channels or in_channels, 3 * TAPS, 3, padding=1)
        self.reset_parameters()

    def reset_parameters(self):
        # DCNv2's initialisation: weights uniform in +-1/sqrt(fan in), bias 0;
        # the offset/mask conv all zeros
        stdv = 1.0 / math.sqrt(self.in_channels * TAPS)
        nn.init.uniform_(self.weight, -stdv, stdv)
        if self.bias is not None:
            nn.init.zeros_(self.bias)
        nn.init.zeros_(self.conv_offset.weight)
        nn.init.zeros_(self.conv_offset.bias)

    def offsets_and_masks(self, guide):
        out = self.conv_offset(guide)
        return out[:, :2 * TAPS], torch.sigmoid(out[:, 2 * TAPS:])

    def forward(self, x, guide):
        offset, mask = self.offsets_and_masks(guide)
        return modulated_deform_conv3x3(x, offset, mask, self.weight, self.bias)


class D2CB(nn.Module):
    """Depth-aware Deformable Convolution Block: the depth feature through two
    1 x 1 conv + LeakyReLU(0.2) layers (the offset network) steers a
    modulated deformable 3 x 3 conv applied to the image feature. The
    group's residual is added by the caller."""

    def __init__(self, channels: int):
        super().__init__()
        self.offset_net = nn.Sequential(nn.Conv2d(channels, channels, 1), nn.LeakyReLU(0.2),
                                        nn.Conv2d(channels, channels, 1), nn.LeakyReLU(0.2))
        self.dcn = ModulatedDeformConv3x3(channels, channels, channels)

    def forward(self, image_feat, depth_feat):
        return self.dcn(image_feat, self.offset_net(depth_feat))
