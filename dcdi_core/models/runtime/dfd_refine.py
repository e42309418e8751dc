"""The learned refinement of the depth read from a capture's blur, run in
numpy (``dfd.estimate_depth(..., refine=...)``): a few 3 x 3 convolutions
over the tile grid of the evidence's features (``dfd.estimate.FEATURES``)
giving a correction of each tile's log depth. The torch side (architecture,
training, export) is ``models.depth.refine``; this file reads what it
exports and never imports torch.
"""
from __future__ import annotations

import math

import numpy as np

from ...io.npzfile import Record, check_array
from ...errors import InputRangeError
from ...errors import ModelFileError
from ...io.model_npz import read_model_npz

FORMAT, VERSION = "dcdi-dfd-refine", 1

# the allowed ranges of a refinement's metadata, checked on load before any
# layer runs (the shipped: 28 channels, 4 layers of 32, 3 x 3 kernels,
# dilations 1-2, 21 hypotheses, 32 px tiles). A convolution pads its input by
# (k // 2) x dilation tiles and makes width x tiles values: these bound what
# one layer allocates to a few times the features' own size.
MAX_CHANNELS = 512             # feature channels in (the estimator's: hypotheses + 7)
MAX_WIDTH = 256                # channels out of a hidden layer
MAX_LAYERS = 16
MAX_DILATION = 16
MAX_KERNEL = 7                 # odd, tiles
MAX_HYPOTHESES = 511
MAX_TILE_PX = 4096


def check_refinement(meta: dict, arrays: dict, fail) -> None:
    """Every field :class:`DfdRefiner` reads, in its range, and each layer's
    weights (out, in, k, k) and bias (out,) chained from ``channels`` to the
    one output (``fail``: ``io.npzfile``'s)."""
    rec = Record(meta, fail)
    rec.name("lens")
    channels = rec.integer("channels", 1, MAX_CHANNELS)
    rec.integer("log_depth_channel", 0, channels - 1)
    dilations = rec.integers("dilations", 1, MAX_DILATION, (1, MAX_LAYERS))
    rec.integer("tile_px", 1, MAX_TILE_PX, optional=True)
    rec.number("pixel_pitch_mm", 0.0, 10.0, lo_open=True, optional=True)
    hyp = rec.numbers("hypotheses_m", 0.0, math.inf, (2, min(MAX_HYPOTHESES, channels)), lo_open=True, inf=True,
                      optional=True)
    if hyp is not None and len(set(hyp)) != len(hyp):
        raise fail("repeats a depth", field="hypotheses_m", allowed="distinct depths (m)")
    c_in = channels
    for i in range(len(dilations)):
        last = i == len(dilations) - 1
        w = arrays.get(f"w{i}")
        n_out = 1 if last else (w.shape[0] if w is not None and w.ndim == 4 else 0)
        k = w.shape[-1] if w is not None and w.ndim == 4 else 0
        if not (1 <= n_out <= MAX_WIDTH and 1 <= k <= MAX_KERNEL and k % 2 == 1):
            raise fail(f"array 'w{i}' is {None if w is None else w.shape}", field=f"w{i}",
                       allowed=f"(out <= {MAX_WIDTH}{', 1 for the last layer' if last else ''}, {c_in}, k, k), "
                               f"k odd <= {MAX_KERNEL}")
        check_array(arrays, f"w{i}", (n_out, c_in, k, k), fail)
        check_array(arrays, f"b{i}", (n_out,), fail)
        c_in = n_out


def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray, dilation: int = 1) -> np.ndarray:
    """'same' convolution of x (C, H, W) by w (O, C, k, k), edges replicated."""
    k = w.shape[-1]
    r = (k // 2) * dilation
    xp = np.pad(x, ((0, 0), (r, r), (r, r)), mode="edge")
    h, wd = x.shape[1:]
    out = np.zeros((w.shape[0], h, wd), np.float32)
    for i in range(k):
        for j in range(k):
            patch = xp[:, i * dilation:i * dilation + h, j * dilation:j * dilation + wd]
            out += np.einsum("oc,chw->ohw", w[:, :, i, j], patch)
    return out + b[:, None, None]


class DfdRefiner:
    """A shipped refinement: ``__call__(features (C, nph, npw)) -> log depth (nph, npw)``."""

    def __init__(self, path):
        self.meta, arrays = read_model_npz(path, FORMAT, VERSION, "depth-from-blur refinement",
                                           check_refinement)
        self.layers = [(arrays[f"w{i}"].astype(np.float32), arrays[f"b{i}"].astype(np.float32), int(d))
                       for i, d in enumerate(self.meta["dilations"])]
        self.path = path

    def check_lens(self, lens_id: str) -> None:
        if self.meta.get("lens") != lens_id:
            raise ModelFileError(self.path, f"trained for lens {self.meta.get('lens')}", field="lens",
                                 allowed=lens_id)

    def check(self, channels: int, tile_px: int, hypotheses: int | None = None) -> None:
        """Refuse features it cannot read: another tile size, or another
        number of channels besides the posterior's (which is resampled onto
        the hypotheses it learned)."""
        if self.meta.get("tile_px", tile_px) != tile_px:
            raise ModelFileError(self.path, f"learned {self.meta.get('tile_px')} px tiles", field="tile_px",
                                 allowed=f"{tile_px} (the estimator's tile)")
        learned = self.meta.get("hypotheses_m")
        extra = self.meta.get("channels") - (len(learned) if learned else 0)
        ours = channels - (hypotheses if hypotheses is not None and learned else 0)
        if extra != ours:
            raise ModelFileError(self.path, f"{self.meta.get('channels')} feature channels", field="channels",
                                 allowed=f"{channels} (features of another estimator version)")

    def resample(self, features: np.ndarray, hypotheses_m) -> np.ndarray:
        """``features`` with their posterior (the first len(hypotheses_m)
        channels) resampled onto the hypotheses it learned, linearly in
        inverse depth (infinity: 0), each tile's sum kept at 1."""
        learned = self.meta.get("hypotheses_m")
        if learned is None or hypotheses_m is None:
            return features
        have = 1.0 / np.asarray(hypotheses_m, float)
        want = 1.0 / np.asarray(learned, float)
        if have.shape == want.shape and np.allclose(have, want, rtol=1e-6, atol=1e-9):
            return features
        post = features[:len(have)]
        order = np.argsort(have)
        flat = post[order].reshape(len(have), -1)
        out = np.stack([np.interp(want, have[order], flat[:, i]) for i in range(flat.shape[1])], 1)
        out /= np.maximum(out.sum(0, keepdims=True), 1e-12)
        return np.concatenate([out.reshape((len(want),) + post.shape[1:]).astype(np.float32),
                               features[len(have):]])

    def __call__(self, features: np.ndarray, hypotheses_m=None) -> np.ndarray:
        """Log depth (nph, npw) from ``features`` (C, nph, npw) of the
        hypotheses ``hypotheses_m`` (None: those it learned)."""
        features = np.asarray(features, np.float32)
        if features.ndim != 3:
            raise InputRangeError("refinement features", features.shape, "(channels, rows, columns)")
        finite_in = bool(np.isfinite(features).all())
        features = self.resample(features, hypotheses_m)
        x = features
        for i, (w, b, d) in enumerate(self.layers):
            x = conv2d(x, w, b, d)
            if i < len(self.layers) - 1:
                x = np.maximum(x, 0.0)
        base = np.asarray(features, np.float32)[self.meta["log_depth_channel"]]
        out = base + x[0]
        bad = ~np.isfinite(out)
        if finite_in and bad.any():
            # finite weights can still overflow: a NaN here would become the far limit everywhere, silently
            # (features the estimator left non-finite pass as they did: the weights are not to blame)
            raise ModelFileError(self.path, f"gave {int(bad.sum())} of {out.size} tiles a non-finite log depth "
                                            "from finite features", field="weights",
                                 allowed="weights that give finite depths")
        return out
