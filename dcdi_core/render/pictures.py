"""Side-by-side pictures: input | depth | result (PNG); whether matplotlib,
which draws them and every other picture (`dcdi psf --png`), is installed.

matplotlib is not a dependency of the wheel (numpy is its only one): an
option that asks for a picture is refused before any work where it is
missing (:func:`require_matplotlib`), in one line saying what to install.
"""
from __future__ import annotations

import numpy as np

from ..atomic import save_figure
from ..errors import DcdiError


class PackageMissingError(DcdiError, ImportError):
    """An optional package that an option needs is not installed (names the
    option and what to install)."""


def require_matplotlib(option: str) -> None:
    """Refuse ``option`` (a picture's option, e.g. ``--side-by-side``, or the
    picture's name) where matplotlib cannot be imported: call it where the
    options are checked, before any work."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise PackageMissingError(f"{option} needs matplotlib, which is not installed: "
                                  "pip install matplotlib") from None


def _srgb(x):
    from ..io.images import linear_to_srgb
    return linear_to_srgb(np.clip(x, 0.0, 1.0))


def side_by_side(path, image, depth, result, title: str) -> None:
    """A PNG with the all-in-focus input, its depth (log scale, invalid grey)
    and the result, sRGB-encoded for viewing."""
    require_matplotlib("a side-by-side picture")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = image.shape[:2]
    fig, axes = plt.subplots(1, 3, figsize=(12, 12 * h / w / 3 + 0.8))
    axes[0].imshow(_srgb(image))
    axes[0].set_title("all-in-focus input", fontsize=9)
    d = np.asarray(depth, dtype=np.float64)
    shown = np.where(d > 0, np.log10(np.clip(d, 0.1, 1e3)), np.nan)
    im = axes[1].imshow(shown, cmap="viridis_r")
    axes[1].set_title("depth (log10 m; grey = invalid)", fontsize=9)
    axes[1].set_facecolor("0.5")
    fig.colorbar(im, ax=axes[1], fraction=0.03)
    axes[2].imshow(_srgb(result))
    axes[2].set_title("result", fontsize=9)
    for a in axes:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def depth_panel(depth_m, near_m: float = 0.5, far_m: float = 20.0) -> np.ndarray:
    """A depth map as a colour image (H, W, 3) in *linear* light, so that
    ``io.images.write_image`` shows it as drawn: viridis (reversed, near
    bright) of log depth over [near_m, far_m], grey where invalid."""
    require_matplotlib("a depth picture")
    import matplotlib

    from ..io.images import srgb_to_linear
    d = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    t = (np.log(np.clip(np.where(valid, d, near_m), near_m, far_m)) - np.log(near_m)) / np.log(far_m / near_m)
    rgb = matplotlib.colormaps["viridis_r"](t)[..., :3]
    rgb[~valid] = 0.5
    return srgb_to_linear(rgb).astype(np.float32)
