"""Shipped network files: a module's state as .npz arrays (no pickle) plus
one JSON string ``meta`` with format, version and a sha256 checksum of all
of it (``runtime.olf.checksum``). numpy only, except :func:`state_arrays`
and :func:`load_state`, which take a torch module."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from .errors import ModelFileError
from .runtime.olf import checksum

DTYPES = ("float16", "float32")


def state_arrays(module, dtype: str = "float16") -> dict:
    """{name: array} of a torch module's state, floating arrays in ``dtype``."""
    if dtype not in DTYPES:
        from ..optics.errors import InputRangeError
        raise InputRangeError("dtype", dtype, " or ".join(DTYPES))
    out = {}
    for k, v in module.state_dict().items():
        a = v.detach().cpu().numpy()
        out[k] = a.astype(dtype) if a.dtype.kind == "f" else a
    return out


def write_model_npz(path, meta: dict, arrays: dict) -> dict:
    """Write ``arrays`` and ``meta`` (its checksum added) atomically; returns meta."""
    meta = dict(meta)
    meta["checksum"] = checksum(meta, arrays)
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **arrays)
    return meta


def read_model_npz(path, fmt: str, version: int, what: str) -> tuple[dict, dict]:
    """(meta, arrays) of a file written by :func:`write_model_npz`, its
    format, version and checksum checked; ``what`` names the kind of file."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise ModelFileError(path, f"no metadata record: not an exported {what}", field="meta")
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except ModelFileError:
        raise
    except (OSError, ValueError) as e:
        raise ModelFileError(path, f"not a readable .npz model file ({e})") from None
    if meta.get("format") != fmt:
        raise ModelFileError(path, f"format {meta.get('format')!r}", field="format", allowed=repr(fmt))
    if meta.get("version") != version:
        raise ModelFileError(path, f"version {meta.get('version')!r}", field="version", allowed=str(version))
    if meta.get("checksum") != checksum(meta, arrays):
        raise ModelFileError(path, "checksum mismatch (the file is corrupt or was edited)", field="checksum")
    return meta, arrays


def load_state(module, arrays: dict, path) -> None:
    """Load float32 copies of ``arrays`` into a torch module (eval mode)."""
    import torch
    state = {k: torch.from_numpy(np.asarray(a, np.float32) if a.dtype.kind == "f" else np.asarray(a))
             for k, a in arrays.items()}
    try:
        module.load_state_dict(state)
    except RuntimeError as e:
        raise ModelFileError(path, f"weights do not fit the recorded network ({str(e)[:200]})") from None
    module.eval()


def trained_pixel_pitch_mm(data_root) -> float | None:
    """The image pixel pitch (mm) of a run's DA2T pairs (their first record), or None."""
    from .data.da2t import finished_pairs
    recs = finished_pairs(data_root) if data_root and Path(data_root).exists() else {}
    pitches = {round(r["pixel_pitch_mm"], 9) for r in recs.values() if "pixel_pitch_mm" in r}
    return next(iter(pitches)) if len(pitches) == 1 else None
