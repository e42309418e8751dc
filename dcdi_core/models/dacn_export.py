"""Shipped DACN weights: a run's checkpoint -> .npz (no pickle) and back.

The file holds the network's state (``float16`` by default: the weights of
a small DACN lose nothing measurable, see the README) and one JSON string
``meta``: format and version, the DACN spec, the training config, the DA2T
settings of its data (the lens, the pixel pitch it learned), the iteration,
the training seconds and the run's validation, with a sha256 checksum of
all of it. Read with ``allow_pickle=False``; :func:`read_dacn_file` checks
format, version and checksum and names what is wrong.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from .errors import ModelFileError
from .runtime.olf import checksum

FORMAT, FORMAT_VERSION = "dcdi-dacn", 1
DTYPES = ("float16", "float32")


def export_dacn(run, path, *, weights: str = "ema", dtype: str = "float16", extra: dict | None = None) -> dict:
    """Write the DACN of ``run`` (a run folder or its checkpoint.pt) to
    ``path`` (.npz); returns the metadata."""
    from .correct import load_dacn

    if dtype not in DTYPES:
        from ..optics.errors import InputRangeError
        raise InputRangeError("dtype", dtype, " or ".join(DTYPES))
    model, info = load_dacn(run, weights=weights)
    arrays = {}
    for k, v in model.state_dict().items():
        a = v.detach().cpu().numpy()
        arrays[k] = a.astype(dtype) if a.dtype.kind == "f" else a
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "spec": info["spec"], "config": info["config"],
            "da2t": info["da2t"], "lens": (info["da2t"] or {}).get("lens"), "step": info["step"],
            "weights": weights, "dtype": dtype, **(extra or {})}
    meta["checksum"] = checksum(meta, arrays)
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **arrays)
    return meta


def read_dacn_file(path) -> tuple[dict, dict]:
    """(metadata, arrays) of an exported DACN, checked."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise ModelFileError(path, "no metadata record: not an exported DACN", field="meta")
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except ModelFileError:
        raise
    except (OSError, ValueError) as e:
        raise ModelFileError(path, f"not a readable .npz model file ({e})") from None
    if meta.get("format") != FORMAT:
        raise ModelFileError(path, f"format {meta.get('format')!r}", field="format", allowed=repr(FORMAT))
    if meta.get("version") != FORMAT_VERSION:
        raise ModelFileError(path, f"version {meta.get('version')!r}", field="version", allowed=str(FORMAT_VERSION))
    if meta.get("checksum") != checksum(meta, arrays):
        raise ModelFileError(path, "checksum mismatch (the file is corrupt or was edited)", field="checksum")
    return meta, arrays
