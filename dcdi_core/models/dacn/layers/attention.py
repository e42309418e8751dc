"""Channel ("transposed") cross-attention between image and depth features,
and RDICAB, the Residual Depth-Image Cross-Attention Block.

The attention runs across channels, not pixels (Restormer's transposed
attention): per head, the (c x c) matrix of cosine similarities between the
query and key channels (each an L2-normalised vector over the pixels), times
a learnable temperature, through a softmax over the keys, mixes the value
channels. Its cost is linear in the pixel count, so it runs on whole
feature maps of any size.
"""
from __future__ import annotations

from ... import require_torch

torch = require_torch()
nn = torch.nn
F = torch.nn.functional


def heads_dividing(channels: int, wanted: int) -> int:
    """The largest head count <= ``wanted`` that divides ``channels``."""
    return next(h for h in range(min(wanted, channels), 0, -1) if channels % h == 0)


class LayerNorm2d(nn.Module):
    """LayerNorm over the channels of each pixel of (N, C, H, W), with weight and bias."""

    def __init__(self, channels: int, eps: float = 1e-5):
        super().__init__()
        self.norm = nn.LayerNorm(channels, eps=eps)

    def forward(self, x):
        return self.norm(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


class ChannelCrossAttention(nn.Module):
    """Q from ``x`` (the image), K and V from ``y`` (the depth), each a 1 x 1
    conv without bias; channel attention per head with L2-normalised Q and K
    and a learnable temperature per head (initialised to 1); a 1 x 1 output
    projection."""

    def __init__(self, channels: int, heads: int = 4):
        super().__init__()
        if channels % heads:
            raise ValueError(f"{channels} channels do not split into {heads} heads")
        self.heads = heads
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.q = nn.Conv2d(channels, channels, 1, bias=False)
        self.k = nn.Conv2d(channels, channels, 1, bias=False)
        self.v = nn.Conv2d(channels, channels, 1, bias=False)
        self.proj = nn.Conv2d(channels, channels, 1, bias=False)

    def forward(self, x, y):
        n, c, h, w = x.shape
        split = lambda t: t.reshape(n, self.heads, c // self.heads, h * w)   # noqa: E731
        q = F.normalize(split(self.q(x)), dim=-1)
        k = F.normalize(split(self.k(y)), dim=-1)
        v = split(self.v(y))
        attn = torch.softmax((q @ k.transpose(-2, -1)) * self.temperature, dim=-1)
        return self.proj((attn @ v).reshape(n, c, h, w))


class MLP(nn.Module):
    """Linear C -> hidden, GELU, hidden -> C, on channels-last tokens."""

    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(channels, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, channels)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class RDICAB(nn.Module):
    """Residual Depth-Image Cross-Attention Block: ``forward(image, depth)``.

    f = image + Attention(LN(image), LN(depth)); f = f + MLP(LN(f)) (C -> 2C,
    GELU, 2C -> C); out = f + image: the paper's long skip (its released
    code's too), so the image feature enters the result twice."""

    def __init__(self, channels: int, heads: int = 4, mlp_ratio: float = 2.0):
        super().__init__()
        self.norm_image = LayerNorm2d(channels)
        self.norm_depth = LayerNorm2d(channels)
        self.attn = ChannelCrossAttention(channels, heads)
        self.norm_mlp = nn.LayerNorm(channels)
        self.mlp = MLP(channels, int(channels * mlp_ratio))

    def forward(self, image, depth):
        if image.shape != depth.shape:
            raise ValueError(f"image features {tuple(image.shape)} and depth features {tuple(depth.shape)} differ")
        f = image + self.attn(self.norm_image(image), self.norm_depth(depth))
        t = f.permute(0, 2, 3, 1)
        t = t + self.mlp(self.norm_mlp(t))
        return t.permute(0, 3, 1, 2) + image
