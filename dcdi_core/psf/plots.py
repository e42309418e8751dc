"""Pictures of PSFs (PNG, matplotlib Agg)."""
from __future__ import annotations

import math

import numpy as np

from ..atomic import save_figure


def psf_rgb(kernel: np.ndarray, gamma: float = 0.5) -> np.ndarray:
    """(3, k, k) -> (k, k, 3) image in [0, 1]: one scale for the three
    channels (so colour fringes show), with a gamma to show faint wings."""
    m = float(kernel.max())
    img = np.moveaxis(kernel, 0, -1) / (m if m > 0 else 1.0)
    return np.clip(img, 0.0, 1.0) ** gamma


def psf_grid_png(kernels, row_labels, col_labels, path, title: str, pixel_pitch_mm: float) -> None:
    """A grid of RGB kernels (rows x cols x 3 x k x k) with labels, as PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kernels = np.asarray(kernels)
    nr, nc = kernels.shape[:2]
    k = kernels.shape[-1]
    fig, axes = plt.subplots(nr, nc, figsize=(1.7 * nc + 0.8, 1.7 * nr + 0.9), squeeze=False)
    for i in range(nr):
        for j in range(nc):
            ax = axes[i, j]
            ax.imshow(psf_rgb(kernels[i, j]), interpolation="nearest", origin="lower")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(col_labels[j], fontsize=8)
            if j == 0:
                ax.set_ylabel(row_labels[i], fontsize=8)
    fig.suptitle(f"{title}\n{k} x {k} px of {pixel_pitch_mm * 1000:.3g} um; each panel scaled to its peak, "
                 "gamma 0.5", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def depth_label(d: float) -> str:
    return "inf" if math.isinf(d) else f"{d:.3g} m"
