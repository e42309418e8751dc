"""Stand-ins of the public depth estimators' packages (Depth Anything V2,
UniDepth, Depth Pro), each with a checkpoint on disk: depth = 1 + 4 x mean
sRGB value, so a test knows the answer."""
from __future__ import annotations

import json
import sys
import types

import numpy as np
import torch


def _stand_in(monkeypatch, name, **attrs):
    mod = types.ModuleType(name)
    for k, v in attrs.items():
        setattr(mod, k, v)
    monkeypatch.setitem(sys.modules, name, mod)
    parent, _, child = name.rpartition(".")
    if parent:
        if parent not in sys.modules:
            monkeypatch.setitem(sys.modules, parent, types.ModuleType(parent))
        monkeypatch.setattr(sys.modules[parent], child, mod, raising=False)
    return mod


class _Net(torch.nn.Module):
    """A stand-in estimator network: depth = 1 + 4 x mean sRGB value."""

    def __init__(self, **kw):
        super().__init__()
        self.kw = kw
        self.scale = torch.nn.Parameter(torch.tensor(4.0))

    def depth_of(self, rgb_uint8_hwc):
        return 1.0 + float(self.scale.detach()) * rgb_uint8_hwc.astype(np.float64).mean(axis=2) / 255.0


def install_stand_ins(monkeypatch, tmp_path) -> dict:
    """Stand-ins of the three public estimators' packages (depth = 1 + 4 x
    mean sRGB value) and a checkpoint for each: {backend: checkpoint}."""
    class DA2(_Net):
        def infer_image(self, bgr, input_size):
            assert bgr.dtype == np.uint8 and input_size == 518
            return self.depth_of(bgr[..., ::-1])
    _stand_in(monkeypatch, "depth_anything_v2.dpt", DepthAnythingV2=DA2)
    ck = tmp_path / "depth_anything_v2_metric_hypersim_vits.pth"
    torch.save(DA2().state_dict(), ck)
    folder = tmp_path / "unidepth"

    class UD(_Net):
        @classmethod
        def from_pretrained(cls, path):
            assert path == str(folder)
            return cls()

        def infer(self, rgb):
            assert rgb.shape[0] == 3 and rgb.dtype == torch.uint8
            return {"depth": torch.from_numpy(self.depth_of(rgb.permute(1, 2, 0).numpy()))[None, None]}
    _stand_in(monkeypatch, "unidepth.models", UniDepthV2=UD, UniDepthV1=UD)
    folder.mkdir(exist_ok=True)
    (folder / "config.json").write_text("{}")
    header = json.dumps({"__metadata__": {}}).encode()
    (folder / "model.safetensors").write_bytes(len(header).to_bytes(8, "little") + header)

    from dataclasses import dataclass

    @dataclass
    class Cfg:
        checkpoint_uri: str = ""

    class DP(_Net):
        def infer(self, x, f_px=None):
            return {"depth": torch.from_numpy(self.depth_of(x))}

    def create(config):
        assert config.checkpoint_uri.endswith("depth_pro.pt")
        return DP(), (lambda u8: u8)
    dp = _stand_in(monkeypatch, "depth_pro", create_model_and_transforms=create)
    dp.depth_pro = types.SimpleNamespace(DEFAULT_MONODEPTH_CONFIG_DICT=Cfg())
    torch.save({"w": torch.zeros(1)}, tmp_path / "depth_pro.pt")
    return {"depth-anything-v2": ck, "unidepth": folder, "depth-pro": tmp_path / "depth_pro.pt"}
