"""The depth network's shipped file (``npz_file``) and its loading from a
run folder, its checkpoint or the .npz."""
from __future__ import annotations

from pathlib import Path

from ...errors import ModelFileError
from ..common.weights_file import load_state, state_arrays, trained_pixel_pitch_mm
from ...io.model_npz import read_model_npz, write_model_npz
from ...io.jsontext import loads

FORMAT, FORMAT_VERSION = "dcdi-depthnet", 1


def load_depthnet(path, *, weights: str = "ema"):
    """(model in eval mode, info) of a depth run folder, checkpoint.pt or .npz."""
    from .arch import DepthNet, DepthNetSpec
    path = Path(path)
    if path.suffix == ".npz":
        meta, arrays = read_model_npz(path, FORMAT, FORMAT_VERSION, "depth network")
        model = DepthNet(DepthNetSpec(**meta["spec"]))
        load_state(model, arrays, path)
        return model, {"meta": meta, "lens": meta.get("lens"), "step": meta["step"]}
    from ..common.checkpoint import load_checkpoint
    ck_path = path / "checkpoint.pt" if path.is_dir() else path
    ck = load_checkpoint(ck_path)
    if ck.get("kind") != "depth":
        raise ModelFileError(ck_path, "not a depth-network checkpoint", field="kind", allowed="depth")
    model = DepthNet(DepthNetSpec(**loads(ck["spec"], f"{ck_path}: spec")))
    model.load_state_dict(ck[weights])
    model.eval()
    config = loads(ck["config"], f"{ck_path}: config")
    da2t = Path(config["data"]) / "da2t.json"
    lens = loads(da2t.read_text(), da2t)["lens"] if da2t.exists() else None
    return model, {"checkpoint": str(ck_path), "step": int(ck["step"]), "config": config, "lens": lens}


def export_depthnet(run, path, *, weights: str = "ema", dtype: str = "float16", extra: dict | None = None) -> dict:
    model, info = load_depthnet(run, weights=weights)
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "spec": model.spec.as_dict(), "config": info["config"],
            "lens": info["lens"], "step": info["step"], "dtype": dtype, "weights": weights,
            "pixel_pitch_mm": trained_pixel_pitch_mm(info["config"].get("data")), **(extra or {})}
    return write_model_npz(path, meta, state_arrays(model, dtype))
