"""DACN, the depth-aware aberration correction network, as data (torch-free).

A :class:`DACNSpec` fixes the architecture; ``CONFIGS`` names the sizes the
project uses, from ``tiny`` (trains in about an hour on 2 CPU cores) to
``paper`` (the released network: C = 180, 6 groups of 6 Swin blocks, the
SwinIR pixel-shuffle tail). The module is ``arch.dacn.DACN``.

Structure (``arch.dacn``): image (N, 3, H, W) and depth (N, 1, H, W, already
encoded: ``data.depth.encode_depth``) padded to a multiple of 4 (of 4 x the
window for RSTB), pixel-unshuffled by 4 (48 and 16 channels); a 3 x 3 conv
48 -> C (the first features) and the depth branch, one 3 x 3 conv 16 -> C
whose output every stage reuses; RDICAB (image x depth cross-attention)
when switched on; G residual groups, each B blocks (``racm``: ``rb``, EDSR
residual blocks, or ``rstb``, Swin blocks), a 3 x 3 conv and, when switched
on, D2CB (a deformable conv steered by the depth feature), plus the group's
input; LayerNorm, a 3 x 3 conv, the skip from the first features; the tail
(``direct``: one 3 x 3 conv C -> 48 and PixelShuffle(4); ``paper``:
SwinIR's conv C -> 64 + LeakyReLU, two (conv 64 -> 256, PixelShuffle(2)),
conv 64 -> 3); plus the input image (global residual); cropped back.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from ...errors import InputRangeError

RACMS = ("rb", "rstb")
TAILS = ("direct", "paper")
DEPTH_ENCODINGS = ("minmax", "diopter")
SCALE = 4            # pixel (un)shuffle factor


@dataclass(frozen=True)
class DACNSpec:
    channels: int = 48                 # C
    groups: int = 2                    # G
    blocks: int = 2                    # B per group
    racm: str = "rstb"                 # the replaceable aberration correction module
    rdicab: bool = True
    d2cb: bool = True
    window: int = 8                    # RSTB window (pixels of the unshuffled map)
    heads: int = 6                     # RSTB heads wanted (the largest count <= this that divides C)
    mlp_ratio: float = 2.0             # RSTB MLP
    rdicab_heads: int = 4
    rdicab_mlp_ratio: float = 2.0
    res_scale: float = 1.0             # RB residual scaling
    tail: str = "direct"
    depth_encoding: str = "minmax"     # how the trainer / inference encode depth for this network
    # the encoded depth and the field maps (runtime.conditioning) as input channels beside the image
    condition: bool = False
    # physics in front: the deconvolved capture is an input too, and the network adds its correction to
    # that instead of to the capture
    refine: bool = False

    def __post_init__(self):
        for name in ("channels", "groups", "blocks", "window", "heads", "rdicab_heads"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InputRangeError(name, v, "an integer >= 1")
        if self.racm not in RACMS:
            raise InputRangeError("racm", self.racm, " or ".join(RACMS))
        if self.tail not in TAILS:
            raise InputRangeError("tail", self.tail, " or ".join(TAILS))
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise InputRangeError("depth_encoding", self.depth_encoding, " or ".join(DEPTH_ENCODINGS))
        for name in ("rdicab", "d2cb", "condition", "refine"):
            if not isinstance(getattr(self, name), bool):
                raise InputRangeError(name, getattr(self, name), "true or false")
        if not (self.mlp_ratio > 0 and self.rdicab_mlp_ratio > 0 and self.res_scale > 0):
            raise InputRangeError("mlp_ratio, rdicab_mlp_ratio, res_scale",
                                  (self.mlp_ratio, self.rdicab_mlp_ratio, self.res_scale), "> 0")

    @property
    def input_channels(self) -> int:
        """Channels before the unshuffle: the image, the deconvolved image
        (refine), encoded depth and the two field maps (condition)."""
        return 3 + 3 * self.refine + 3 * self.condition

    @property
    def depth_branch(self) -> bool:
        """The depth feature branch that RDICAB and D2CB read (networks made
        before conditioning carry it even with both off)."""
        return self.rdicab or self.d2cb or not self.condition

    @property
    def multiple(self) -> int:
        """Inputs are padded to a multiple of this many pixels."""
        return SCALE * (self.window if self.racm == "rstb" else 1)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DACNSpec":
        return cls(**d)


CONFIGS = {
    # C = 48, 2 x 2 Swin blocks, the cheap tail: 0.27 M parameters
    "tiny": DACNSpec(channels=48, groups=2, blocks=2, racm="rstb"),
    # the ablation's RACM (the paper's tables: RB), at tiny cost
    "tiny-rb": DACNSpec(channels=48, groups=2, blocks=2, racm="rb"),
    # what this machine trains well: plain 3 x 3 convs at a quarter resolution, the depth and field as
    # input channels, refining the deconvolution (models/dacn's study chose it by held-out PSNR per CPU-hour)
    "refine": DACNSpec(channels=64, groups=3, blocks=2, racm="rb", rdicab=False, d2cb=False,
                       depth_encoding="diopter", condition=True, refine=True),
    # the released code's demo configuration (C = 60, 4 x 6)
    "demo": DACNSpec(channels=60, groups=4, blocks=6, racm="rstb", tail="paper"),
    # the released configuration (C = 180, 6 x 6)
    "paper": DACNSpec(channels=180, groups=6, blocks=6, racm="rstb", tail="paper"),
}


def named(name: str, **overrides) -> DACNSpec:
    """A named configuration, optionally with fields replaced."""
    if name not in CONFIGS:
        raise InputRangeError("DACN config", name, ", ".join(CONFIGS))
    return replace(CONFIGS[name], **overrides) if overrides else CONFIGS[name]
