"""Shipped DACN weights: a run's checkpoint -> .npz (no pickle) and back.

The file (``npz_file``) holds the network's state (``float16`` by default)
and its metadata: the DACN spec, the training config, the DA2T settings of
its data (the lens, the pixel pitch it learned), the iteration and the
weights kind. Read with ``allow_pickle=False``; format, version and
checksum are checked and what is wrong is named.
"""
from __future__ import annotations

from ..common.weights_file import state_arrays, trained_pixel_pitch_mm
from ...io.model_npz import write_model_npz
from ..runtime.dacn_file import FORMAT, FORMAT_VERSION
from .correct import load_dacn


def export_dacn(run, path, *, weights: str = "ema", dtype: str = "float16", extra: dict | None = None) -> dict:
    """Write the DACN of ``run`` (a run folder or its checkpoint.pt) to
    ``path`` (.npz); returns the metadata."""
    model, info = load_dacn(run, weights=weights)
    arrays = state_arrays(model, dtype)
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "spec": info["spec"], "config": info["config"],
            "da2t": info["da2t"], "lens": (info["da2t"] or {}).get("lens"), "step": info["step"],
            "weights": weights, "dtype": dtype,
            "pixel_pitch_mm": trained_pixel_pitch_mm(info["config"].get("data")), **(extra or {})}
    return write_model_npz(path, meta, arrays)

