"""What every shipped .npz with a JSON ``meta`` record shares (the networks'
files, the PSF bases): the checksum over the record and the arrays, and a
cache that reads a file once until it changes on disk. numpy only."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path


def checksum(meta: dict, arrays: dict) -> str:
    """sha256 of the metadata (without its checksum) and every array (name, dtype, shape, bytes)."""
    import numpy as np
    h = hashlib.sha256()
    h.update(json.dumps({k: v for k, v in meta.items() if k != "checksum"}, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


class FileCache:
    """``load(path)`` kept for the next request of the same file (its
    resolved path, size and modification time), at most ``size`` files; a
    file changed on disk is read again. ``stat`` errors pass to the caller."""

    def __init__(self, load, size: int):
        self._load, self._size, self._kept = load, size, {}

    def __call__(self, path):
        path = Path(path)
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
        if key not in self._kept:
            if len(self._kept) >= self._size:
                self._kept.clear()
            self._kept[key] = self._load(path)
        return self._kept[key]
