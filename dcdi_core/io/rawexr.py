"""A small numpy-only reader for uncompressed scanline OpenEXR files.

Inside Blender the PyPI OpenImageIO clashes with Blender's own, and Blender's
image API gives Python no access to a multilayer file's passes (only the
first). The Blender add-on therefore renders to an *uncompressed* (codec
NONE) multilayer EXR and reads every channel here, with numpy and the
standard library only. Single-part files (Blender 3.x / 4.x multilayer) and
multi-part files (Blender 5 writes one part per pass) are both read.

Format facts used (OpenEXR "File Layout" document): magic 20000630, a
version word whose bit 0x1000 marks multi-part; each header is a list of
(name, type, size, value) attributes ended by an empty name; multi-part
headers end with an empty header; then one offset table per part
(``chunkCount`` entries, or one per scanline block for single-part files);
an uncompressed scanline chunk is [part number (multi-part only)], y, byte
count, then for each line the channels in name order, each a run of
``width`` samples (HALF 2 bytes, FLOAT and UINT 4 bytes, little-endian).
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

MAGIC = 20000630
_PIXEL_TYPES = {0: ("<u4", 4), 1: ("<f2", 2), 2: ("<f4", 4)}      # UINT, HALF, FLOAT
_NO_COMPRESSION = 0


class RawExrError(ValueError):
    """An EXR file this reader cannot read; the message names the file and why."""

    def __init__(self, path, why: str):
        super().__init__(f"{path}: {why}")


def _cstr(buf: bytes, pos: int, path) -> tuple[str, int]:
    end = buf.find(b"\0", pos)
    if end < 0:
        raise RawExrError(path, "truncated header (unterminated name)")
    return buf[pos:end].decode("latin-1"), end + 1


def _header(buf: bytes, pos: int, path) -> tuple[dict, int]:
    """Attributes from ``pos`` to the empty name; returns (attributes, next pos)."""
    attrs = {}
    while True:
        name, pos = _cstr(buf, pos, path)
        if not name:
            return attrs, pos
        typ, pos = _cstr(buf, pos, path)
        (size,) = struct.unpack_from("<i", buf, pos)
        pos += 4
        attrs[name] = (typ, buf[pos:pos + size])
        pos += size


def _channels(raw: bytes, path) -> list[tuple[str, int]]:
    out, pos = [], 0
    while pos < len(raw) and raw[pos] != 0:
        name, pos = _cstr(raw, pos, path)
        ptype = struct.unpack_from("<i", raw, pos)[0]
        xs, ys = struct.unpack_from("<ii", raw, pos + 8)
        if ptype not in _PIXEL_TYPES:
            raise RawExrError(path, f"channel {name!r} has pixel type {ptype} (allowed 0 UINT, 1 HALF, 2 FLOAT)")
        if (xs, ys) != (1, 1):
            raise RawExrError(path, f"channel {name!r} is subsampled ({xs}, {ys}); only (1, 1) is read")
        out.append((name, ptype))
        pos += 16
    return sorted(out)          # stored in name order whatever the list says


def read_exr_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of an uncompressed scanline EXR as (H, W) float32 arrays,
    keyed by channel name (multi-part: parts' channels merged; a name that
    repeats is prefixed with the part's name). Rows are top to bottom."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise RawExrError(path, f"cannot read the file ({e.strerror})") from None
    if len(buf) < 8 or struct.unpack_from("<i", buf, 0)[0] != MAGIC:
        raise RawExrError(path, "not an OpenEXR file (bad magic number)")
    flags = struct.unpack_from("<I", buf, 4)[0]
    multi = bool(flags & 0x1000)
    if flags & 0x200:
        raise RawExrError(path, "tiled EXR; only scanline files are read")
    if flags & 0x800:
        raise RawExrError(path, "deep EXR; only flat scanline files are read")
    pos = 8
    headers = []
    while True:
        h, pos = _header(buf, pos, path)
        headers.append(h)
        if not multi:
            break
        if buf[pos] == 0:           # the empty header ends the list
            pos += 1
            break
    parts = []
    for i, h in enumerate(headers):
        for key in ("channels", "compression", "dataWindow"):
            if key not in h:
                raise RawExrError(path, f"part {i} has no {key!r} attribute")
        comp = h["compression"][1][0]
        if comp != _NO_COMPRESSION:
            raise RawExrError(path, f"part {i} uses compression {comp}; only 0 (NONE) is read "
                                    "(render with image_settings.exr_codec = 'NONE')")
        if "type" in h and h["type"][1].rstrip(b"\0") not in (b"scanlineimage",):
            raise RawExrError(path, f"part {i} is of type {h['type'][1]!r}; only scanlineimage is read")
        x0, y0, x1, y1 = struct.unpack("<iiii", h["dataWindow"][1])
        ny = y1 - y0 + 1
        n_chunks = struct.unpack("<i", h["chunkCount"][1])[0] if "chunkCount" in h else ny
        name = h["name"][1].rstrip(b"\0").decode("latin-1") if "name" in h else ""
        parts.append((name, _channels(h["channels"][1], path), x1 - x0 + 1, ny, y0, n_chunks))
    offsets = []
    for (_, _, _, _, _, n) in parts:
        offsets.append(np.frombuffer(buf, "<u8", n, pos))
        pos += 8 * n
    out: dict[str, np.ndarray] = {}
    for p, (pname, chans, w, ny, y0, _) in enumerate(parts):
        line_bytes = sum(_PIXEL_TYPES[t][1] for _, t in chans) * w
        planes = {c: np.empty((ny, w), np.float32) for c, _ in chans}
        head = 12 if multi else 8
        for off in offsets[p]:
            off = int(off)
            y, size = struct.unpack_from("<ii", buf, off + head - 8)
            if size != line_bytes or off + head + size > len(buf):
                raise RawExrError(path, f"part {p}: chunk at byte {off} holds {size} bytes, expected {line_bytes} "
                                        "(one uncompressed scanline)")
            row, at = y - y0, off + head
            for c, t in chans:
                dt, nb = _PIXEL_TYPES[t]
                planes[c][row] = np.frombuffer(buf, dt, w, at)
                at += nb * w
        for c, a in planes.items():
            out[f"{pname}.{c}" if c in out else c] = a
    return out
