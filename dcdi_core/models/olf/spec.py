"""The Omni-Lens-Field as data: variant, sizes, inputs and layer shapes.

Torch-free: the trainer builds its module from an :class:`OLFSpec`, the
exporter writes the spec into the file's metadata, and the numpy runtime
reads it back.

Two variants:

``paper`` (the paper's released network): inputs (patch row / (rows - 1),
patch column / (cols - 1), depth in m / max depth, lens index / (lenses -
1)) on a grid of 16-px patches of a 1280 x 1920 image; Linear 4 -> W/4, ReLU,
W/4 -> W, ReLU, N x (W -> W, ReLU), three heads W -> k^2 (one per colour)
with a Sigmoid; trained on peak-normalised PSFs (max 1 per channel, not sum 1).

``radial`` (ours): the lenses are rotationally symmetric, so a PSF depends on
the field radius and the depth only and is rotated to the patch azimuth when
a PSF map is made (as the library's kernels are). Inputs: field radius,
inverse depth / diopter_scale, optionally the focus distance's inverse /
diopter_scale, and the lens as one-hot. The trunk is shared; each lens has a
head W -> 3 k^2 with its own k (a lens with a large blur needs more pixels),
and the output is a softmax over the k^2 pixels of each channel: non-negative
and summing to 1 per channel by construction.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from ...errors import ModelError
from ...errors import InputRangeError

VARIANTS = ("paper", "radial")


def check_variant_and_lenses(variant: str, lenses: tuple) -> None:
    """The OLF variant is one of VARIANTS and the lenses are one or more distinct ids."""
    if variant not in VARIANTS:
        raise InputRangeError("variant", variant, " or ".join(VARIANTS))
    if not lenses or len(set(lenses)) != len(lenses):
        raise InputRangeError("lenses", lenses, "one or more distinct lens ids")

# named sizes: (hidden layers N, width W); the first layer is W // 4 wide
# (the paper's 512 for W = 2048)
SIZES = {
    "tiny": (1, 64),
    "small": (2, 256),
    "medium": (3, 512),
    "large": (4, 1024),
    "paper": (5, 2048),
}

# the paper's grid: 16-px patches of a 1280 x 1920 image, depths to 10 m
PAPER_GRID = {"height": 1280, "width": 1920, "patch": 16, "max_depth_m": 10.0}


@dataclass(frozen=True)
class OLFSpec:
    """One Omni-Lens-Field network: what goes in, what comes out, how big."""

    variant: str
    lenses: tuple[str, ...]              # lens ids, in input order (paper: lens index; radial: one-hot)
    kernel_sizes: tuple[int, ...]        # k per lens (paper: one k for all)
    hidden_layers: int = 5
    width: int = 2048
    first_width: int | None = None       # None: width // 4
    focus: bool = False                  # radial: the focus distance is an input
    diopter_scale: float = 1.0 / 0.7     # radial: inverse depths (1/m) are divided by this
    paper_grid: dict = field(default_factory=lambda: dict(PAPER_GRID))

    def __post_init__(self):
        object.__setattr__(self, "lenses", tuple(self.lenses))
        object.__setattr__(self, "kernel_sizes", tuple(int(k) for k in self.kernel_sizes))
        check_variant_and_lenses(self.variant, self.lenses)
        if len(self.kernel_sizes) != len(self.lenses):
            raise InputRangeError("kernel_sizes", self.kernel_sizes, f"one per lens ({len(self.lenses)})")
        for k in self.kernel_sizes:
            if k < 1 or k % 2 == 0:
                raise InputRangeError("kernel_size", k, "odd integer >= 1")
        if self.variant == "paper":
            if len(set(self.kernel_sizes)) != 1:
                raise InputRangeError("kernel_sizes", self.kernel_sizes, "one k for all lenses (paper variant)")
            if self.focus:
                raise InputRangeError("focus", self.focus, "False for the paper variant (its inputs have no focus)")
        if self.hidden_layers < 0:
            raise InputRangeError("hidden_layers", self.hidden_layers, ">= 0")
        if self.width < 1 or self.first_width_ < 1:
            raise InputRangeError("width", (self.first_width, self.width), ">= 1 (and width // 4 >= 1)")
        if not self.diopter_scale > 0:
            raise InputRangeError("diopter_scale", self.diopter_scale, "> 0 (1/m)")

    @classmethod
    def sized(cls, variant: str, lenses, kernel_sizes, size: str, **kw) -> "OLFSpec":
        if size not in SIZES:
            raise InputRangeError("size", size, ", ".join(SIZES))
        n, w = SIZES[size]
        return cls(variant, tuple(lenses), tuple(kernel_sizes), hidden_layers=n, width=w, **kw)

    @property
    def first_width_(self) -> int:
        return self.first_width if self.first_width is not None else self.width // 4

    @property
    def n_inputs(self) -> int:
        if self.variant == "paper":
            return 4
        return 2 + int(self.focus) + len(self.lenses)

    def trunk_shapes(self) -> list[tuple[int, int]]:
        """(in, out) of each trunk Linear (each followed by ReLU)."""
        w, f = self.width, self.first_width_
        return [(self.n_inputs, f), (f, w)] + [(w, w)] * self.hidden_layers

    def head_shapes(self) -> list[tuple[int, int]]:
        """(in, out) of each head Linear: paper: three (W, k^2), shared by the
        lenses; radial: one (W, 3 k^2) per lens."""
        if self.variant == "paper":
            k = self.kernel_sizes[0]
            return [(self.width, k * k)] * 3
        return [(self.width, 3 * k * k) for k in self.kernel_sizes]

    def param_count(self) -> int:
        return sum(i * o + o for i, o in self.trunk_shapes() + self.head_shapes())

    def lens_index(self, lens_id: str) -> int:
        try:
            return self.lenses.index(lens_id)
        except ValueError:
            raise ModelError(f"lens {lens_id!r} is not one this OLF learned ({', '.join(self.lenses)})") from None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["lenses"] = list(self.lenses)
        d["kernel_sizes"] = list(self.kernel_sizes)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "OLFSpec":
        return cls(**d)
