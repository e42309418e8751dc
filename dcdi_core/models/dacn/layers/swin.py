"""Swin transformer blocks (Liu et al. 2021, as SwinIR uses them) for feature
maps of any size.

A block: LayerNorm, window multi-head self-attention with a learned relative
position bias (windows of w x w pixels; every second block shifted by w / 2
with a cyclic roll), a residual, LayerNorm, MLP, a residual. Maps whose size
is not a multiple of w are zero-padded at the bottom and right for the
attention and cropped back; the attention mask keeps every real pixel from
attending to padding as well as (in shifted blocks) to pixels that the roll
brought from the far side of the map. Tensors are channels-last (N, H, W, C).
"""
from __future__ import annotations

from ... import require_torch
from .attention import MLP

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

MASKED = -100.0      # added to the logits of pairs that may not attend (exp(-100) ~ 0)


def window_partition(x, w: int):
    """(N, H, W, C) with H, W multiples of w -> (N * H/w * W/w, w * w, C)."""
    n, h, ww, c = x.shape
    x = x.view(n, h // w, w, ww // w, w, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, w * w, c)


def window_merge(windows, w: int, n: int, h: int, ww: int):
    """The inverse of :func:`window_partition`."""
    c = windows.shape[-1]
    x = windows.view(n, h // w, ww // w, w, w, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(n, h, ww, c)


def _labels(size: int, padded: int, w: int, shift: int):
    """Per position of the rolled, padded axis: its band (0 unrolled, 1 and 2
    the last window's two parts when shifted) and whether it is padding."""
    pos = torch.arange(padded)
    band = torch.zeros(padded, dtype=torch.long)
    if shift:
        band[padded - w:padded - shift] = 1
        band[padded - shift:] = 2
    pad = (pos + shift) % padded >= size
    return band, pad


def attention_mask(h: int, ww: int, w: int, shift: int):
    """(windows, w*w, w*w) additive mask for an (h, ww) map padded to
    multiples of w and rolled by -shift, or None when nothing is masked."""
    hp, wp = -(-h // w) * w, -(-ww // w) * w
    if shift == 0 and hp == h and wp == ww:
        return None
    bh, ph = _labels(h, hp, w, shift)
    bw, pw = _labels(ww, wp, w, shift)
    label = (bh[:, None] * 3 + bw[None, :]) + 9 * (ph[:, None] | pw[None, :])
    lw = window_partition(label.view(1, hp, wp, 1).float(), w).squeeze(-1)      # (windows, w*w)
    differs = lw[:, None, :] != lw[:, :, None]
    return torch.zeros(differs.shape).masked_fill(differs, MASKED)


class WindowAttention(nn.Module):
    """Multi-head self-attention inside w x w windows with relative position bias."""

    def __init__(self, dim: int, window: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"{dim} channels do not split into {heads} heads")
        self.dim, self.window, self.heads = dim, window, heads
        self.scale = (dim // heads) ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.relative_position_bias = nn.Parameter(torch.zeros((2 * window - 1) ** 2, heads))
        nn.init.trunc_normal_(self.relative_position_bias, std=0.02)
        coords = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)
        rel = (coords[:, :, None] - coords[:, None, :]) + (window - 1)          # (2, n, n) in [0, 2w-2]
        self.register_buffer("relative_index", rel[0] * (2 * window - 1) + rel[1], persistent=False)

    def forward(self, x, mask=None):
        b, n, c = x.shape
        qkv = self.qkv(x).view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
        attn = q @ k.transpose(-2, -1)
        bias = self.relative_position_bias[self.relative_index.reshape(-1)].view(n, n, -1).permute(2, 0, 1)
        attn = attn + bias.unsqueeze(0)
        if mask is not None:
            nw = mask.shape[0]
            attn = (attn.view(b // nw, nw, self.heads, n, n) + mask.to(attn.dtype)[None, :, None]).view(b, self.heads, n, n)
        attn = torch.softmax(attn, dim=-1)
        return self.proj((attn @ v).transpose(1, 2).reshape(b, n, c))


class SwinBlock(nn.Module):
    """One Swin transformer block on (N, H, W, C); ``shift`` 0 or window // 2."""

    def __init__(self, dim: int, heads: int, window: int = 8, shift: int = 0, mlp_ratio: float = 2.0):
        super().__init__()
        if not 0 <= shift < window:
            raise ValueError(f"shift {shift} outside [0, {window})")
        self.window, self.shift = window, shift
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, window, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = MLP(dim, int(dim * mlp_ratio))
        self._masks = {}

    def _mask(self, h, w, device):
        key = (h, w, str(device))
        if key not in self._masks:
            m = attention_mask(h, w, self.window, self.shift)
            self._masks[key] = None if m is None else m.to(device)
        return self._masks[key]

    def forward(self, x):
        n, h, w, c = x.shape
        ws, s = self.window, self.shift
        y = self.norm1(x)
        hp, wp = -(-h // ws) * ws, -(-w // ws) * ws
        if hp != h or wp != w:
            y = F.pad(y, (0, 0, 0, wp - w, 0, hp - h))
        if s:
            y = torch.roll(y, shifts=(-s, -s), dims=(1, 2))
        y = self.attn(window_partition(y, ws), self._mask(h, w, x.device))
        y = window_merge(y, ws, n, hp, wp)
        if s:
            y = torch.roll(y, shifts=(s, s), dims=(1, 2))
        x = x + y[:, :h, :w]
        return x + self.mlp(self.norm2(x))


class SwinStack(nn.Module):
    """``depth`` Swin blocks on (N, C, H, W), every second one shifted."""

    def __init__(self, dim: int, depth: int, heads: int, window: int = 8, mlp_ratio: float = 2.0):
        super().__init__()
        self.blocks = nn.ModuleList(SwinBlock(dim, heads, window, 0 if i % 2 == 0 else window // 2, mlp_ratio)
                                    for i in range(depth))

    def forward(self, x):
        t = x.permute(0, 2, 3, 1)
        for blk in self.blocks:
            t = blk(t)
        return t.permute(0, 3, 1, 2)
