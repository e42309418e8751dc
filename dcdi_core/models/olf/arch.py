"""The Omni-Lens-Field MLP (torch). Built from an :class:`~.spec.OLFSpec`;
takes inputs already encoded by ``psf.olf.encode_*`` (one encoding for
training and serving)."""
from __future__ import annotations

from .. import require_torch
from .spec import OLFSpec

torch = require_torch()
nn = torch.nn


class OLF(nn.Module):
    """x (B, n_inputs) -> PSFs.

    paper: (B, 3, k, k) in (0, 1), peak-normalised targets.
    radial: ``forward(x, lens)`` with ``lens`` (B,) int lens indices ->
    a list over the spec's lenses of (n_l, 3, k_l, k_l) for the rows of that
    lens (in their order in the batch), each channel summing to 1; or, with
    one int ``lens``, (B, 3, k, k).
    """

    def __init__(self, spec: OLFSpec):
        super().__init__()
        self.spec = spec
        layers = []
        for i, o in spec.trunk_shapes():
            layers += [nn.Linear(i, o), nn.ReLU()]
        self.trunk = nn.Sequential(*layers)
        self.heads = nn.ModuleList(nn.Linear(i, o) for i, o in spec.head_shapes())
        for m in self.modules():
            if isinstance(m, nn.Linear):
                # the paper's initialisation: Kaiming uniform weights, zero biases
                nn.init.kaiming_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        if spec.variant == "radial":
            for h in self.heads:       # start from flat kernels; biases set from data by the trainer
                nn.init.zeros_(h.weight)

    def features(self, x):
        return self.trunk(x)

    def head_logits(self, feat, lens: int):
        """radial: unnormalised log-PSF (B, 3, k^2) of lens index ``lens``."""
        k = self.spec.kernel_sizes[lens]
        return self.heads[lens](feat).view(-1, 3, k * k)

    def forward(self, x, lens=None):
        feat = self.trunk(x)
        if self.spec.variant == "paper":
            k = self.spec.kernel_sizes[0]
            out = torch.cat([torch.sigmoid(h(feat)) for h in self.heads], dim=1)
            return out.view(-1, 3, k, k)
        if isinstance(lens, int):
            k = self.spec.kernel_sizes[lens]
            return torch.softmax(self.head_logits(feat, lens), dim=-1).view(-1, 3, k, k)
        outs = []
        for li, k in enumerate(self.spec.kernel_sizes):
            rows = (lens == li).nonzero().flatten()
            logits = self.head_logits(feat[rows], li)
            outs.append(torch.softmax(logits, dim=-1).view(-1, 3, k, k))
        return outs


def count_parameters(module) -> int:
    return sum(p.numel() for p in module.parameters())
