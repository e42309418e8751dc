"""Shipped network files: a module's state as .npz arrays (no pickle) plus
one JSON string ``meta`` with format, version and a sha256 checksum of all
of it (``io.npzfile.checksum``, as the PSF bases). numpy only: writing them from a torch
module and loading them into one is ``models.common.weights_file``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...atomic import atomic_path
from ..errors import ModelFileError
from .olf import checksum, read_npz_with_meta

DTYPES = ("float16", "float32")


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
    meta, arrays = read_npz_with_meta(path, what)
    if meta.get("format") != fmt:
        raise ModelFileError(path, f"format {meta.get('format')!r}", field="format", allowed=repr(fmt))
    if meta.get("version") != version:
        raise ModelFileError(path, f"version {meta.get('version')!r}", field="version", allowed=str(version))
    if meta.get("checksum") != checksum(meta, arrays):
        raise ModelFileError(path, "checksum mismatch (the file is corrupt or was edited)", field="checksum")
    return meta, arrays
