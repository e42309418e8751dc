"""DACN (torch): built from a :class:`~.dacn_spec.DACNSpec` (see there for
the structure). ``forward(image, depth)``: image (N, 3, H, W) linear RGB,
depth (N, 1, H, W) encoded (``data.depth.encode_depth``), any H, W ->
corrected (N, 3, H, W)."""
from __future__ import annotations

from .. import require_torch
from .spec import SCALE, DACNSpec

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

from .layers.attention import RDICAB, LayerNorm2d, heads_dividing  # noqa: E402
from .layers.blocks import ResBlock  # noqa: E402
from .layers.deform_conv import D2CB  # noqa: E402
from .layers.swin import SwinStack  # noqa: E402


class ResidualGroup(nn.Module):
    """B blocks, a 3 x 3 conv, D2CB (when on) steered by the depth feature,
    plus the group's input."""

    def __init__(self, spec: DACNSpec):
        super().__init__()
        c = spec.channels
        if spec.racm == "rstb":
            self.body = SwinStack(c, spec.blocks, heads_dividing(c, spec.heads), spec.window, spec.mlp_ratio)
        else:
            self.body = nn.Sequential(*(ResBlock(c, spec.res_scale) for _ in range(spec.blocks)))
        self.conv = nn.Conv2d(c, c, 3, padding=1)
        self.d2cb = D2CB(c) if spec.d2cb else None

    def forward(self, x, depth_feat):
        y = self.conv(self.body(x))
        if self.d2cb is not None:
            y = self.d2cb(y, depth_feat)
        return y + x


class PaperTail(nn.Module):
    """SwinIR's classical-SR upsampler: conv C -> 64 + LeakyReLU, two (conv
    64 -> 256, PixelShuffle(2)), conv 64 -> 3."""

    def __init__(self, channels: int, feat: int = 64):
        super().__init__()
        self.before = nn.Sequential(nn.Conv2d(channels, feat, 3, padding=1), nn.LeakyReLU(0.01))
        self.up = nn.Sequential(nn.Conv2d(feat, 4 * feat, 3, padding=1), nn.PixelShuffle(2),
                                nn.Conv2d(feat, 4 * feat, 3, padding=1), nn.PixelShuffle(2))
        self.last = nn.Conv2d(feat, 3, 3, padding=1)

    def forward(self, x):
        return self.last(self.up(self.before(x)))


def pad_to_multiple(x, multiple: int):
    """Pad (N, C, H, W) at the bottom and right to multiples of ``multiple``
    (reflected where the map is large enough, else replicated)."""
    h, w = x.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    if ph == 0 and pw == 0:
        return x
    mode = "reflect" if ph < h and pw < w else "replicate"
    return F.pad(x, (0, pw, 0, ph), mode=mode)


class DACN(nn.Module):
    def __init__(self, spec: DACNSpec):
        super().__init__()
        self.spec = spec
        c = spec.channels
        self.unshuffle = nn.PixelUnshuffle(SCALE)
        self.conv_first = nn.Conv2d(spec.input_channels * SCALE * SCALE, c, 3, padding=1)
        self.conv_depth = nn.Conv2d(SCALE * SCALE, c, 3, padding=1) if spec.depth_branch else None
        self.rdicab = RDICAB(c, heads_dividing(c, spec.rdicab_heads), spec.rdicab_mlp_ratio) if spec.rdicab else None
        self.norm_in = LayerNorm2d(c) if spec.racm == "rstb" else None     # SwinIR's patch norm
        self.groups = nn.ModuleList(ResidualGroup(spec) for _ in range(spec.groups))
        self.norm_out = LayerNorm2d(c)
        self.conv_after_body = nn.Conv2d(c, c, 3, padding=1)
        if spec.tail == "direct":
            self.tail = nn.Sequential(nn.Conv2d(c, 3 * SCALE * SCALE, 3, padding=1), nn.PixelShuffle(SCALE))
        else:
            self.tail = PaperTail(c)
        self.apply(_init)
        # the last conv starts at zero: the untrained network returns its input
        # (the global residual), and training starts from the capture's error
        last = self.tail[0] if spec.tail == "direct" else self.tail.last
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, image, depth, deconvolved=None, field=None):
        """image (N, 3, H, W) linear; depth (N, 1, H, W) encoded; with
        ``spec.refine`` the deconvolved image (N, 3, H, W), with
        ``spec.condition`` the field maps (N, 2, H, W)."""
        n, _, h, w = image.shape if image.ndim == 4 else (0, 0, 0, 0)
        want = {"image": (image, 3), "depth": (depth, 1)}
        if self.spec.refine:
            want["deconvolved"] = (deconvolved, 3)
        if self.spec.condition:
            want["field"] = (field, 2)
        for name, (t, c) in want.items():
            if t is None or image.ndim != 4 or tuple(t.shape) != (n, c, h, w):
                raise ValueError(f"{name} {None if t is None else tuple(t.shape)}: expected (N, {c}, H, W) with "
                                 f"the image's N, H, W ({tuple(image.shape)}; the spec's refine={self.spec.refine}, "
                                 f"condition={self.spec.condition})")
        m = self.spec.multiple
        parts = [image] + ([deconvolved] if self.spec.refine else []) + ([depth, field] if self.spec.condition else [])
        x = self.unshuffle(pad_to_multiple(torch.cat(parts, 1) if len(parts) > 1 else image, m))
        d = self.conv_depth(self.unshuffle(pad_to_multiple(depth, m))) if self.conv_depth is not None else None
        first = self.conv_first(x)
        f = self.rdicab(first, d) if self.rdicab is not None else first
        if self.norm_in is not None:
            f = self.norm_in(f)
        for g in self.groups:
            f = g(f, d)
        f = self.conv_after_body(self.norm_out(f)) + first
        base = deconvolved if self.spec.refine else image
        return self.tail(f)[..., :h, :w] + base


def _init(m):
    # SwinIR's: truncated-normal linear weights (std 0.02), zero biases; LayerNorm 1 / 0
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


def count_parameters(module) -> int:
    return sum(p.numel() for p in module.parameters())
