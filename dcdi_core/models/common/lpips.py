"""LPIPS (Zhang et al. 2018, v0.1, AlexNet) in plain torch, from weights on
the user's disk.

LPIPS needs pretrained weights that cannot be had here (no network, and
torchvision does not load beside this torch): the AlexNet backbone as
torchvision saves it (``alexnet-owt-7be5be79.pth``: ``features.<i>.weight``
and ``.bias``) and the LPIPS linear layers of the ``lpips`` package
(``weights/v0.1/alex.pth``: ``lin<k>.model.1.weight``). Give both paths.

The distance of two images in [0, 1]: sRGB-encode (LPIPS was learned on
display images; ours are linear), scale to [-1, 1], shift and scale per
channel, AlexNet's five ReLU outputs, each unit-normalised over channels,
squared difference, the non-negative 1x1 linear layer, upsampled to the
image size and summed over layers: a spatial map whose mean over the
scored pixels is the LPIPS (the package's ``spatial=True``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import require_torch
from ...errors import ModelFileError

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
CHANNELS = (64, 192, 384, 256, 256)
TAPS = (1, 4, 7, 9, 11)            # indices of AlexNet's ReLUs in ``features``


def alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU())


class LPIPS(nn.Module):
    def __init__(self):
        super().__init__()
        self.features = alexnet_features()
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    def taps(self, x):
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in TAPS:
                out.append(x)
        return out

    def forward(self, a, b):
        """Spatial LPIPS map (B, 1, H, W) of display images a, b in [0, 1]."""
        h, w = a.shape[-2:]
        fa, fb = (self.taps(((2 * x - 1) - self.shift) / self.scale) for x in (a, b))
        total = 0
        for lin, xa, xb in zip(self.lins, fa, fb):
            na = xa / (xa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = xb / (xb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + F.interpolate(lin((na - nb) ** 2), size=(h, w), mode="bilinear", align_corners=False)
        return total


def _state(path, what: str) -> dict:
    p = Path(path)
    if not p.exists():
        raise ModelFileError(p, f"no such {what} file")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure: name the file
        raise ModelFileError(p, f"not a readable {what} file ({str(e)[:160]})") from None
    if not isinstance(state, dict):
        raise ModelFileError(p, f"not a {what} state dict")
    return state


def load_lpips(backbone_path, lin_path) -> LPIPS:
    """LPIPS (AlexNet, v0.1) from torchvision's AlexNet weights and the lpips
    package's linear layers; a file that does not fit is named."""
    model = LPIPS()
    bb = _state(backbone_path, "AlexNet backbone (torchvision alexnet-owt-*.pth)")
    feats = {k[len("features."):]: v for k, v in bb.items() if k.startswith("features.")}
    lins = _state(lin_path, "LPIPS linear-layer (lpips weights/v0.1/alex.pth)")
    lin_state = {f"{k}.weight": lins.get(f"lin{k}.model.1.weight") for k in range(len(CHANNELS))}
    try:
        model.features.load_state_dict(feats)
    except RuntimeError as e:
        raise ModelFileError(backbone_path, f"not AlexNet's features ({str(e)[:160]})") from None
    if any(v is None for v in lin_state.values()):
        raise ModelFileError(lin_path, "no lin<k>.model.1.weight entries (not the lpips package's alex.pth)")
    try:
        model.lins.load_state_dict(lin_state)
    except RuntimeError as e:
        raise ModelFileError(lin_path, f"linear layers of the wrong shape ({str(e)[:160]})") from None
    return model.eval()


def lpips_score(model: LPIPS, a, b, mask=None) -> float:
    """LPIPS of (H, W, 3) linear images in [0, 1], the mean of its map over
    ``mask`` (H, W) bool (default: every pixel)."""
    from ...io.images import linear_to_srgb
    x, y = (torch.from_numpy(np.ascontiguousarray(
        np.clip(linear_to_srgb(np.clip(i, 0, 1)), 0, 1).transpose(2, 0, 1), dtype=np.float32))[None] for i in (a, b))
    with torch.no_grad():
        m = model(x, y)[0, 0].numpy()
    return float(m[mask].mean() if mask is not None else m.mean())
