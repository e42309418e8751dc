"""The demo's scenes: all-in-focus RGB (linear) with metric depth, and where
the frame lies on the camera lens's sensor.

Both are placed at the pixel pitch the correction and depth networks learned
(their training frames spanned the sensor at 480 x 640): the built-in
synthetic scene as the sensor's centre crop at that pitch, the factory sample
as rendered (the factory's camera spans the sensor at its resolution; at
another resolution the pipeline notes the pitch it was not trained on).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputRangeError


@dataclass
class Scene:
    key: str                 # file-name stem of its pictures: 'synthetic', 'factory'
    title: str               # what it is, for the report
    aif: np.ndarray          # (H, W, 3) float32 linear, all in focus
    depth_m: np.ndarray      # (H, W) float32 planar metres (NaN invalid, inf infinity)
    geometry: object         # render.geometry.ImageGeometry of the frame on the camera lens's sensor


def synthetic_scene(camera, size: tuple[int, int], pixel_pitch_mm: float) -> Scene:
    """The built-in synthetic RGB-D scene (``render.synthetic``) of ``size``
    (rows, cols), centred on ``camera``'s sensor at ``pixel_pitch_mm``."""
    from ..render.geometry import ImageGeometry
    from ..render.base import check_within_sensor
    from ..render.synthetic import synthetic_rgbd

    h, w = (int(v) for v in size)
    if h < 32 or w < 32:
        raise InputRangeError("synthetic scene size", (h, w), "at least 32 x 32 px")
    geometry = ImageGeometry.from_pixel_pitch(camera, h, w, pixel_pitch_mm)
    check_within_sensor(geometry, f"the {h} x {w} synthetic scene at {pixel_pitch_mm * 1000:.4g} um")
    aif, depth = synthetic_rgbd(h, w, seed=0)
    return Scene("synthetic", f"built-in synthetic scene, {h} x {w}, the centre of {camera.id}'s sensor",
                 aif, depth, geometry)


def factory_scene(folder, camera) -> Scene:
    """The first finished sample of a dataset-factory folder, rendered by
    ``camera`` across its sensor; a folder of another camera lens is refused."""
    from ..dataset.rgbd import FactoryFolder
    from ..render.geometry import ImageGeometry

    source = FactoryFolder(folder)
    ids = source.ids()
    if not ids:
        raise InputRangeError(f"factory folder {folder}", "no finished sample", "at least one (manifest.jsonl)")
    frame = source.load(ids[0])
    rendered_by = frame.meta.get("manifest", {}).get("camera_lens")
    if rendered_by != camera.id:
        raise InputRangeError(f"camera lens of {Path(folder) / 'manifest.jsonl'} ({ids[0]})", rendered_by,
                              f"{camera.id}, the demo's camera lens (--lens {camera.id})")
    recipe = frame.meta.get("manifest", {}).get("recipe", "factory")
    h, w = frame.depth.shape
    return Scene("factory", f"dataset-factory sample {ids[0]} ({recipe} recipe, Blender Cycles), {h} x {w}, "
                            f"across {camera.id}'s sensor",
                 frame.image, frame.depth, ImageGeometry.full_sensor(camera, h, w))
