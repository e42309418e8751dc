"""Depth estimators: ``estimate(image) -> depth`` in metres.

``image`` is (H, W, 3) linear RGB (what ``io.images.read_image`` returns);
the result is (H, W) float32 metres, finite and positive. Backends:

- ``dcdi``: the project's depth network (``arch.depthnet``), from an
  exported .npz (the shipped ``weights/depth-<lens>.npz``) or a run folder.
- ``unidepth``: UniDepth V1/V2 (``pip install`` its repository,
  github.com/lpiccinelli-eth/UniDepth); the checkpoint is the local folder
  that ``UniDepthV2.from_pretrained`` reads (``config.json`` and
  ``model.safetensors``), downloaded beforehand by the user.
- ``depth-anything-v2``: Depth Anything V2's *metric* models
  (github.com/DepthAnything/Depth-Anything-V2, ``metric_depth`` on
  ``sys.path``); the checkpoint a ``depth_anything_v2_metric_<set>_<enc>.pth``;
  encoder and max depth from its name (hypersim: 20 m, vkitti: 80 m).
- ``depth-pro``: Apple's Depth Pro (github.com/apple/ml-depth-pro); the
  checkpoint its ``depth_pro.pt``.

A checkpoint is read (its container checked) before the backend's package is
imported, so a wrong or damaged file is named at once; nothing is fetched
from the network: the packages' own download paths are never taken.
"""
from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from ...errors import InputRangeError
from ...errors import ModelError, ModelFileError
from ...io.jsontext import loads

BACKENDS = ("dcdi", "unidepth", "depth-anything-v2", "depth-pro")


class DepthEstimator:
    """Metric depth of an image. Subclasses set ``name`` and ``_estimate``."""

    name = "depth"

    def estimate(self, image) -> np.ndarray:
        img = np.asarray(image, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 8:
            raise InputRangeError("image shape", img.shape, "(H, W, 3) with H, W >= 8")
        if not np.isfinite(img).all():
            raise InputRangeError("image", "NaN or infinite pixels", "finite values")
        d = np.asarray(self._estimate(img), dtype=np.float64)
        if d.shape != img.shape[:2]:
            raise ModelError(f"{self.name}: depth of shape {d.shape} for an image of {img.shape[:2]}")
        if not np.isfinite(d).all() or (d <= 0).any():
            raise ModelError(f"{self.name}: the estimate has {int((~np.isfinite(d) | (d <= 0)).sum())} "
                             "non-finite or non-positive pixels")
        return d.astype(np.float32)

    def _estimate(self, img: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


def srgb_uint8(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear -> sRGB uint8, what the public estimators were trained on."""
    from ...io.images import linear_to_srgb
    return np.round(np.clip(linear_to_srgb(np.clip(img, 0.0, 1.0)), 0.0, 1.0) * 255.0).astype(np.uint8)


# ------------------------------------------------------------- checkpoints
def check_torch_file(path: Path, backend: str) -> dict:
    """The state dict in a torch checkpoint (loaded with weights_only), or a
    ModelFileError naming the file and the backend."""
    from .. import require_torch
    torch = require_torch()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure: name the file
        raise ModelFileError(path, f"not a readable {backend} checkpoint ({str(e)[:160]})") from None
    if isinstance(state, dict) and isinstance(state.get("model"), dict):
        state = state["model"]
    if not isinstance(state, dict) or not state:
        raise ModelFileError(path, f"not a {backend} checkpoint (no weights in it)")
    return state


def check_safetensors(path: Path, backend: str) -> dict:
    """The header of a .safetensors file (8-byte length, JSON), checked."""
    try:
        with open(path, "rb") as f:
            n = struct.unpack("<Q", f.read(8))[0]
            if not 2 <= n <= 100_000_000:
                raise ValueError(f"header length {n}")
            header = loads(f.read(n), path)
    except (OSError, ValueError, struct.error) as e:
        raise ModelFileError(path, f"not a readable {backend} safetensors file ({e})") from None
    return header


def _existing(path, backend: str) -> Path:
    if path is None:
        raise InputRangeError(f"{backend} checkpoint", None, "a path on this disk (it is never downloaded)")
    p = Path(path)
    if not p.exists():
        raise ModelFileError(p, f"no such {backend} checkpoint")
    return p


def _package(module: str, backend: str, how: str):
    import importlib
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ModelError(f"{backend} needs its package '{module}' ({e}); {how}") from None


# ---------------------------------------------------------------- backends
class DCDIDepth(DepthEstimator):
    """The project's depth network: an exported .npz or a run folder."""

    name = "dcdi"

    def __init__(self, path, threads: int = 1):
        from .. import require_torch
        torch = require_torch()
        torch.set_num_threads(threads)
        from .export import load_depthnet
        self.model, self.info = load_depthnet(_existing(path, self.name))

    def _estimate(self, img):
        from .train import predict_depth
        return predict_depth(self.model, img)


class UniDepth(DepthEstimator):
    name = "unidepth"

    def __init__(self, path, version: str = "v2"):
        p = _existing(path, self.name)
        if not p.is_dir() or not (p / "config.json").exists():
            raise ModelFileError(p, "not a UniDepth checkpoint folder (needs config.json and model.safetensors "
                                    "as from_pretrained writes them)")
        weights = p / "model.safetensors"
        if weights.exists():
            check_safetensors(weights, self.name)
        elif (p / "pytorch_model.bin").exists():
            check_torch_file(p / "pytorch_model.bin", self.name)
        else:
            raise ModelFileError(p, "no model.safetensors or pytorch_model.bin in the UniDepth folder")
        models = _package("unidepth.models", self.name, "install UniDepth: pip install "
                          "git+https://github.com/lpiccinelli-eth/UniDepth")
        cls = getattr(models, "UniDepthV2" if version == "v2" else "UniDepthV1")
        self.model = cls.from_pretrained(str(p)).eval()

    def _estimate(self, img):
        import torch
        rgb = torch.from_numpy(srgb_uint8(img)).permute(2, 0, 1)
        with torch.no_grad():
            out = self.model.infer(rgb)
        return out["depth"].squeeze().cpu().numpy()


DA2_CONFIGS = {"vits": (64, [48, 96, 192, 384]), "vitb": (128, [96, 192, 384, 768]),
               "vitl": (256, [256, 512, 1024, 1024])}


class DepthAnythingV2(DepthEstimator):
    name = "depth-anything-v2"

    def __init__(self, path, encoder: str | None = None, max_depth: float | None = None, input_size: int = 518):
        p = _existing(path, self.name)
        m = re.search(r"metric_(hypersim|vkitti)_(vits|vitb|vitl)", p.name)
        encoder = encoder or (m.group(2) if m else None)
        if encoder not in DA2_CONFIGS:
            raise InputRangeError("depth-anything-v2 encoder", encoder, ", ".join(DA2_CONFIGS) +
                                  " (or a file named depth_anything_v2_metric_<hypersim|vkitti>_<encoder>.pth)")
        max_depth = max_depth or (80.0 if m and m.group(1) == "vkitti" else 20.0)
        state = check_torch_file(p, self.name)
        dpt = _package("depth_anything_v2.dpt", self.name, "clone github.com/DepthAnything/Depth-Anything-V2 "
                       "and put its metric_depth folder on PYTHONPATH")
        features, out_channels = DA2_CONFIGS[encoder]
        self.model = dpt.DepthAnythingV2(encoder=encoder, features=features, out_channels=out_channels,
                                         max_depth=max_depth)
        try:
            self.model.load_state_dict(state)
        except RuntimeError as e:
            raise ModelFileError(p, f"weights do not fit Depth Anything V2 {encoder} ({str(e)[:160]})") from None
        self.model.eval()
        self.input_size = input_size

    def _estimate(self, img):
        bgr = srgb_uint8(img)[..., ::-1].copy()          # its infer_image takes OpenCV's BGR
        return np.asarray(self.model.infer_image(bgr, self.input_size))


class DepthPro(DepthEstimator):
    name = "depth-pro"

    def __init__(self, path, f_px: float | None = None):
        p = _existing(path, self.name)
        check_torch_file(p, self.name)
        dp = _package("depth_pro", self.name, "install Depth Pro: pip install git+https://github.com/apple/ml-depth-pro")
        from dataclasses import replace
        config = replace(dp.depth_pro.DEFAULT_MONODEPTH_CONFIG_DICT, checkpoint_uri=str(p))
        self.model, self.transform = dp.create_model_and_transforms(config=config)
        self.model.eval()
        self.f_px = f_px

    def _estimate(self, img):
        import torch
        with torch.no_grad():
            out = self.model.infer(self.transform(srgb_uint8(img)), f_px=self.f_px)
        return out["depth"].squeeze().cpu().numpy()


CLASSES = {"dcdi": DCDIDepth, "unidepth": UniDepth, "depth-anything-v2": DepthAnythingV2, "depth-pro": DepthPro}


def load_estimator(backend: str, checkpoint, **options) -> DepthEstimator:
    """The estimator ``backend`` (one of BACKENDS) from ``checkpoint``."""
    if backend not in CLASSES:
        raise InputRangeError("depth backend", backend, ", ".join(BACKENDS))
    return CLASSES[backend](checkpoint, **options)
