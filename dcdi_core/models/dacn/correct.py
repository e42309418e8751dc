"""Aberration correction with a trained DACN (torch), tiled for any size.

``load_dacn(RUN or checkpoint.pt)`` rebuilds the network from the
checkpoint's spec with its EMA weights (or the raw ones). ``correct(model,
image, depth_m)``: the image is cut into tiles of ``tile`` px overlapping by
``overlap`` px; each tile's result is weighted by a ramp over the overlap
(rising from the tile's edges) and the weighted sum divided by the weights,
so neighbouring tiles cross-fade and leave no seam; memory is bounded by one
tile. The depth is encoded once for the whole image (min-max over the whole
image, not per tile), so tiles share one depth scale. An image that fits one
tile is one forward pass, exactly as without tiling. The tiles run on the
model's device (``load_dacn(..., device=)``: auto, cpu, cuda[:N]); the
result comes back to the CPU.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import require_torch
from ..runtime.depth_encoding import encode_depth, minmax_stats
from ...errors import ModelFileError
from ...errors import InputRangeError

torch = require_torch()
from .arch import DACN  # noqa: E402
from .spec import DACNSpec  # noqa: E402
from ..common.checkpoint import load_checkpoint  # noqa: E402
from ...io.jsontext import loads
from ..runtime.dacn_file import read_dacn_file


def load_dacn(path, *, weights: str = "ema", device: str = "cpu"):
    """(model in eval mode on ``device``, info) from a run folder, its
    checkpoint.pt or an exported .npz (``dacn_export``; ``weights`` is then
    the file's); ``device`` is refused (naming --device) before the file is
    read when CUDA is asked for and torch sees none."""
    from ..common.distributed import describe, resolve_device
    dev = resolve_device(device)
    path = Path(path)
    if path.suffix == ".npz":
        return _load_exported(path, dev, describe(dev))
    ck_path = path / "checkpoint.pt" if path.is_dir() else path
    ck = load_checkpoint(ck_path)
    if ck.get("kind") != "dacn":
        raise ModelFileError(ck_path, "not a DACN checkpoint", field="kind", allowed="dacn")
    if weights not in ("ema", "model"):
        raise InputRangeError("weights", weights, "'ema' or 'model'")
    spec = DACNSpec.from_dict(loads(ck["spec"], f"{ck_path}: spec"))
    model = DACN(spec)
    model.load_state_dict(ck[weights])
    model.to(dev).eval()
    config = loads(ck["config"], f"{ck_path}: config")
    da2t = Path(config["data"]) / "da2t.json"
    info = {"checkpoint": str(ck_path), "step": int(ck["step"]), "spec": spec.as_dict(), "config": config,
            "weights": weights, "device": describe(dev),
            "da2t": loads(da2t.read_text(), da2t) if da2t.exists() else None}
    return model, info


def _load_exported(path: Path, dev, device_name: str):
    from ..common.weights_file import load_state
    meta, arrays = read_dacn_file(path)
    spec = DACNSpec.from_dict(meta["spec"])
    model = DACN(spec)
    load_state(model, arrays, path)
    model.to(dev)
    info = {"checkpoint": str(path), "step": int(meta["step"]), "spec": spec.as_dict(), "config": meta["config"],
            "weights": meta["weights"], "device": device_name, "da2t": meta.get("da2t"), "meta": meta}
    return model, info


def _ramp(n: int, overlap: int) -> np.ndarray:
    i = np.arange(n, dtype=np.float64)
    if overlap <= 0:
        return np.ones(n)
    return np.minimum(1.0, np.minimum(i + 0.5, n - i - 0.5) / overlap)


def _starts(size: int, tile: int, step: int) -> list[int]:
    if size <= tile:
        return [0]
    s = list(range(0, size - tile, step)) + [size - tile]
    return sorted(set(s))


def network_inputs(spec, image, depth_m, *, deconvolved=None, geometry=None, field=None) -> list:
    """The arrays (C, H, W) float32 a network of ``spec`` reads, in its
    forward's order (image, encoded depth[, deconvolved][, field]), for a
    whole image: depth encoded once over the image (minmax: its own range),
    the field maps of the image's pixels from ``geometry``
    (``render.geometry.ImageGeometry``; or ``field`` maps given). Training
    crops get the same from ``data.PairCrops`` (tested equal)."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("image shape", img.shape, "(H, W, 3)")
    d = np.asarray(depth_m)
    if d.shape != img.shape[:2]:
        raise InputRangeError("depth map shape", d.shape, f"{img.shape[:2]}, the image's")
    enc = spec.depth_encoding
    out = [img.transpose(2, 0, 1), encode_depth(d, enc, stats=minmax_stats(d) if enc == "minmax" else None)[None]]
    if spec.refine:
        if deconvolved is None or np.shape(deconvolved) != img.shape:
            raise InputRangeError("deconvolved image", None if deconvolved is None else np.shape(deconvolved),
                                  f"{img.shape}: this network refines the deconvolution (correct.deconvolution)")
        out.append(np.asarray(deconvolved, np.float32).transpose(2, 0, 1))
    if spec.condition:
        if field is None:
            if geometry is None:
                raise InputRangeError("geometry", None, "where the image lies on the sensor: this network is "
                                      "told each pixel's field")
            if (geometry.height, geometry.width) != img.shape[:2]:
                raise InputRangeError("geometry size", (geometry.height, geometry.width), f"{img.shape[:2]}")
            from ..runtime.conditioning import geometry_field_maps
            field = geometry_field_maps(geometry)
        if np.shape(field) != (2, *img.shape[:2]):
            raise InputRangeError("field maps", np.shape(field), f"(2, {img.shape[0]}, {img.shape[1]})")
        out.append(np.asarray(field, np.float32))
    return out


def correct(model, image, depth_m, *, deconvolved=None, geometry=None, field=None, tile: int = 256,
            overlap: int = 32, progress=None) -> np.ndarray:
    """The corrected (H, W, 3) float32 image of ``image`` (H, W, 3) linear
    with metric ``depth_m`` (H, W); a refining network also reads the
    ``deconvolved`` image, a conditioned one the field of each pixel
    (``geometry``: where the image lies on the sensor; see
    ``network_inputs``). progress(done, total) after each tile."""
    if tile < 8 or not 0 <= overlap < tile // 2 + 1:
        raise InputRangeError("tile, overlap", (tile, overlap), "tile >= 8, 0 <= overlap <= tile / 2")
    inputs = network_inputs(model.spec, image, depth_m, deconvolved=deconvolved, geometry=geometry, field=field)
    h, w = inputs[0].shape[1:]
    rows, cols = _starts(h, tile, tile - overlap), _starts(w, tile, tile - overlap)
    total = len(rows) * len(cols)
    device = next(model.parameters()).device
    names = ["image", "depth"] + (["deconvolved"] if model.spec.refine else []) + (
        ["field"] if model.spec.condition else [])

    def run(r, c, th, tw):
        t = {n: torch.from_numpy(np.ascontiguousarray(a[:, r:r + th, c:c + tw]))[None].to(device)
             for n, a in zip(names, inputs)}
        with torch.no_grad():
            return model(t["image"], t["depth"], t.get("deconvolved"), t.get("field"))[0].cpu().numpy().transpose(
                1, 2, 0)

    if total == 1:
        out = run(0, 0, h, w)
        if progress:
            progress(1, 1)
        return out.astype(np.float32)
    acc = np.zeros((h, w, 3), np.float64)
    wsum = np.zeros((h, w, 1), np.float64)
    done = 0
    for r in rows:
        th = min(tile, h)
        for c in cols:
            tw = min(tile, w)
            wt = (_ramp(th, overlap if len(rows) > 1 else 0)[:, None]
                  * _ramp(tw, overlap if len(cols) > 1 else 0)[None, :])[..., None]
            acc[r:r + th, c:c + tw] += wt * run(r, c, th, tw)
            wsum[r:r + th, c:c + tw] += wt
            done += 1
            if progress:
                progress(done, total)
    return (acc / wsum).astype(np.float32)
