"""A built-in synthetic RGB-D scene (seeded): textures at several depths.

For the demo, the tests and the reports: a textured background wall far away
(beyond the far limit), a ground plane receding from 0.8 m to 12 m, a
textured board at 3 m, a red disk at 1.2 m in front of it, and small bright
lights (bokeh balls) at 6 m. Linear RGB in [0, 1], depth in metres.
"""
from __future__ import annotations

import numpy as np


def _texture(rng, h, w, scale):
    """Band-limited noise with fine detail, in [0, 1]."""
    base = rng.random((h // scale + 2, w // scale + 2))
    ys = np.linspace(0, base.shape[0] - 1.001, h)
    xs = np.linspace(0, base.shape[1] - 1.001, w)
    y0, x0 = ys.astype(int), xs.astype(int)
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    b = base
    smooth = ((1 - fy) * (1 - fx) * b[y0][:, x0] + (1 - fy) * fx * b[y0][:, x0 + 1]
              + fy * (1 - fx) * b[y0 + 1][:, x0] + fy * fx * b[y0 + 1][:, x0 + 1])
    fine = rng.random((h, w))
    return np.clip(0.7 * smooth + 0.3 * fine, 0.0, 1.0)


def synthetic_rgbd(height: int = 240, width: int = 360, seed: int = 0, *, disk: bool = True):
    """(image (H, W, 3) float32 linear, depth (H, W) float32 metres).
    ``disk=False`` leaves out the red disk: the scene behind it, which the
    occlusion measurement uses as ground truth."""
    rng = np.random.default_rng(seed)
    h, w = height, width
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.empty((h, w, 3))
    depth = np.full((h, w), 1e10)                          # the wall: Blender's background value
    wall = _texture(rng, h, w, 12)
    img[...] = np.stack([0.25 * wall, 0.35 * wall, 0.55 * wall + 0.1], -1)
    horizon = 0.55 * h
    ground = yy > horizon
    t = (yy - horizon) / (h - horizon)                     # 0 at the horizon, 1 at the bottom
    gd = 1.0 / (1.0 / 12.0 + t * (1.0 / 0.8 - 1.0 / 12.0))  # uniform in inverse depth
    depth = np.where(ground, gd, depth)
    checker = ((np.floor(xx / 8) + np.floor(yy / 8)) % 2)[..., None]
    img = np.where(ground[..., None], 0.15 + 0.5 * checker * np.array([0.6, 0.5, 0.3]), img)
    board = (np.abs(xx - 0.3 * w) < 0.18 * w) & (np.abs(yy - 0.42 * h) < 0.22 * h)
    depth = np.where(board, 3.0, depth)
    stripes = 0.5 + 0.5 * np.sign(np.sin(xx / 3.0))
    img = np.where(board[..., None], np.stack([0.2 + 0.6 * stripes, 0.2 + 0.6 * stripes, 0.2 + 0.5 * stripes], -1), img)
    disk = ((xx - 0.62 * w) ** 2 + (yy - 0.5 * h) ** 2 < (0.14 * h) ** 2) & disk
    depth = np.where(disk, 1.2, depth)
    disk_tex = _texture(rng, h, w, 6)       # drawn either way: the same seed gives the same scene behind
    img = np.where(disk[..., None], np.array([0.8, 0.08, 0.05]) * (0.6 + 0.4 * disk_tex)[..., None], img)
    for _ in range(6):                                       # small bright lights at 6 m
        cy, cx = rng.uniform(0.1, 0.45) * h, rng.uniform(0.05, 0.95) * w
        spot = (yy - cy) ** 2 + (xx - cx) ** 2 < 1.5 ** 2
        depth = np.where(spot, 6.0, depth)
        img = np.where(spot[..., None], np.array([1.0, 0.95, 0.8]), img)
    return img.astype(np.float32), depth.astype(np.float32)
