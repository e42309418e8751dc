"""Filling and upsampling a per-tile inverse-depth map by its confidence,
edge-aware on the capture: confident tiles spread into uncertain ones
(normalised convolution, widening until a tile has confident neighbours),
then a guided filter (He et al. 2013) with the capture's luminance as guide
brings the tiles' values to pixels, following the capture's edges.

Units: inverse depth in 1/m; radii in tiles or pixels as named.
"""
from __future__ import annotations

import numpy as np


def box(x: np.ndarray, r: int) -> np.ndarray:
    """Mean over the (2r + 1)^2 square about each pixel of the last two
    axes, the square shrunk at the borders (cumulative sums)."""
    def along(a, axis):
        n = a.shape[axis]
        c = np.cumsum(a, axis=axis, dtype=np.float64)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        i = np.arange(n)
        hi, lo = np.minimum(i + r + 1, n), np.maximum(i - r, 0)
        return (np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)) / (hi - lo).reshape(
            [-1 if k == (axis % a.ndim) else 1 for k in range(a.ndim)])
    return along(along(np.asarray(x, np.float64), -2), -1)


def spread(value: np.ndarray, weight: np.ndarray, scales=(1, 2, 4, 8, 16), enough: float = 0.2) -> np.ndarray:
    """Each tile's value where its weight (0-1) is high, else the weighted
    mean of its neighbourhood, the smallest square (radius in ``scales``,
    tiles) that holds a weight of at least ``enough`` per tile; the
    largest square's mean where none does (the global mean beyond it)."""
    w = np.clip(weight, 0.0, 1.0)
    out = np.full(value.shape, np.nan)
    glob = (w * value).sum() / w.sum() if w.sum() > 0 else float(np.mean(value))
    for r in scales:
        den = box(w, r)
        mean = box(w * value, r) / np.maximum(den, 1e-12)
        take = np.isnan(out) & (den >= enough)
        out[take] = mean[take]
    out[np.isnan(out)] = glob
    return w * value + (1.0 - w) * out


def upsample(tiles: np.ndarray, stride: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear from tile centres (tile (i, j) centred at ((i + 0.5) stride,
    (j + 0.5) stride) px) to every pixel of ``shape``; held at the borders."""
    h, w = shape
    nph, npw = tiles.shape

    def coords(n, count):
        t = (np.arange(n) + 0.5) / stride - 0.5
        t = np.clip(t, 0, count - 1)
        i0 = np.minimum(np.floor(t).astype(int), max(count - 2, 0))
        i1 = np.minimum(i0 + 1, count - 1)
        return i0, i1, t - i0

    r0, r1, fr = coords(h, nph)
    c0, c1, fc = coords(w, npw)
    top = tiles[r0][:, c0] * (1 - fc) + tiles[r0][:, c1] * fc
    bottom = tiles[r1][:, c0] * (1 - fc) + tiles[r1][:, c1] * fc
    return top * (1 - fr)[:, None] + bottom * fr[:, None]


def guided(guide: np.ndarray, src: np.ndarray, r: int, eps: float) -> np.ndarray:
    """He et al.'s guided filter of ``src`` (H, W) by a grey ``guide`` (H, W), radius r px."""
    mg, ms = box(guide, r), box(src, r)
    cov = box(guide * src, r) - mg * ms
    var = box(guide * guide, r) - mg * mg
    a = cov / (var + eps)
    b = ms - a * mg
    return box(a, r) * guide + box(b, r)


def luminance_guide(capture: np.ndarray) -> np.ndarray:
    """The capture's luminance on a log scale (edges of dark and bright
    regions alike), normalised to unit spread."""
    lum = np.asarray(capture, np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    g = np.log(np.maximum(lum, 0.0) + 1e-3)
    s = g.std()
    return (g - g.mean()) / (s if s > 0 else 1.0)


def tile_colours(capture: np.ndarray, stride: int, shape_tiles: tuple[int, int]) -> np.ndarray:
    """Each tile's median log colour (nph, npw, 3) over its stride x stride
    pixels (edge tiles padded by reflection): the colour of the surface
    covering most of it, not a mix of both sides of an edge."""
    nph, npw = shape_tiles
    h, w = capture.shape[:2]
    logc = np.log(np.maximum(np.asarray(capture, np.float32), 0.0) + 1e-3)
    pad = np.pad(logc, ((0, nph * stride - h), (0, npw * stride - w), (0, 0)), mode="symmetric")
    blocks = pad.reshape(nph, stride, npw, stride, 3).transpose(0, 2, 4, 1, 3).reshape(nph, npw, 3, -1)
    return np.median(blocks, axis=-1)


def joint_bilateral(value: np.ndarray, weight: np.ndarray, tile_colour: np.ndarray, capture: np.ndarray,
                    stride: int, radius: int = 1, sigma_colour: float = 0.15, floor: float = 0.05) -> np.ndarray:
    """Per pixel, the mean of the tiles' ``value`` (nph, npw) within
    ``radius`` tiles of it, each weighted by a tent on its distance from the
    pixel (tile units), by how alike its colour (``tile_colour``, log RGB)
    is to the pixel's in ``capture`` (Gaussian of scale ``sigma_colour``)
    and by its ``weight`` (plus ``floor``): joint bilateral upsampling
    (Kopf et al. 2007), so that a depth edge follows the image's colour
    edge inside a tile instead of a blend across it. (H, W) float64."""
    h, w = capture.shape[:2]
    nph, npw = value.shape
    logc = np.log(np.maximum(np.asarray(capture, np.float32), 0.0) + 1e-3)
    ty = (np.arange(h) + 0.5) / stride - 0.5                  # pixel centres in tile coordinates
    tx = (np.arange(w) + 0.5) / stride - 0.5
    iy, ix = np.floor(ty).astype(int), np.floor(tx).astype(int)
    num = np.zeros((h, w))
    den = np.zeros((h, w))
    wt = np.clip(weight, 0.0, 1.0) + floor
    for dy in range(-radius + 1, radius + 1):
        ry = np.clip(iy + dy, 0, nph - 1)
        sy = np.maximum(0.0, 1.0 - np.abs(ty - (iy + dy)) / radius)
        for dx in range(-radius + 1, radius + 1):
            rx = np.clip(ix + dx, 0, npw - 1)
            sx = np.maximum(0.0, 1.0 - np.abs(tx - (ix + dx)) / radius)
            c = tile_colour[ry][:, rx]                                      # (h, w, 3)
            d2 = ((logc - c) ** 2).sum(-1)
            k = np.exp(-d2 / (2 * sigma_colour ** 2)) * (sy[:, None] * sx[None, :]) * wt[ry][:, rx] + 1e-12
            num += k * value[ry][:, rx]
            den += k
    return num / den
