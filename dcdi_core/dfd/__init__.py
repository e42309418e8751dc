"""Depth from the capture itself: the camera lens's own depth-varying blur
(depth from defocus and chromatic aberration) read with the lens's PSFs.
Numpy only: it runs where the deconvolution runs, Blender's Python included.

- ``evidence``: per window, the likelihood of its spectrum under each depth's PSFs;
- ``estimate``: the options, the per-tile choice and its confidence, the filled depth map;
- ``fill``: confident tiles spread into uncertain ones along the capture's edges.
"""
from .estimate import DepthEstimate, DepthFromBlurOptions, estimate_depth

__all__ = ["DepthEstimate", "DepthFromBlurOptions", "estimate_depth"]
