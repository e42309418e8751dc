"""Crafted files for the hostile-input tests: small on disk, huge in what
they claim (EXR windows and zlib bombs, PNG headers, .npy headers)."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from dcdi_core.io import rawexr

_ZIP = 3                    # 16 scanlines a chunk


def _header(channels, data_window, display_window, compression=_ZIP) -> bytes:
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for n in sorted(channels)) + b"\0"
    attrs = [rawexr._attr("channels", "chlist", chlist),
             rawexr._attr("compression", "compression", bytes([compression])),
             rawexr._attr("dataWindow", "box2i", struct.pack("<iiii", *data_window)),
             rawexr._attr("displayWindow", "box2i", struct.pack("<iiii", *display_window)),
             rawexr._attr("lineOrder", "lineOrder", b"\0"),
             rawexr._attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
             rawexr._attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
             rawexr._attr("screenWindowWidth", "float", struct.pack("<f", 1.0))]
    return struct.pack("<iI", rawexr.MAGIC, 2) + b"".join(sorted(attrs)) + b"\0"


def _assemble(header: bytes, chunks: list) -> bytes:
    pos = len(header) + 8 * len(chunks)
    offsets = []
    for c in chunks:
        offsets.append(pos)
        pos += len(c)
    return header + np.asarray(offsets, "<u8").tobytes() + b"".join(chunks)


def _zeros_deflated(n: int) -> bytes:
    """zlib of ``n`` bytes of the ZIP predictor's zero (128 after the first: a flat image), streamed."""
    z = zlib.compressobj(9)
    out = [z.compress(b"\0")]
    step = b"\x80" * (1 << 24)
    left = n - 1
    while left > 0:
        out.append(z.compress(step[:min(left, len(step))]))
        left -= len(step)
    out.append(z.flush())
    return b"".join(out)


def constant_exr(path, height: int, width: int, channels=("Z",)) -> Path:
    """A flat ``height`` x ``width`` float EXR (ZIP) built chunk by chunk,
    never holding its pixels: a 20000 x 20000 depth map is about 2 MB."""
    header = _header(channels, (0, 0, width - 1, height - 1), (0, 0, width - 1, height - 1))
    line = 4 * width * len(channels)
    full = _zeros_deflated(16 * line)
    chunks = []
    for y in range(0, height, 16):
        n = min(16, height - y)
        data = full if n == 16 else _zeros_deflated(n * line)
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    Path(path).write_bytes(_assemble(header, chunks))
    return Path(path)


def zip_bomb_exr(path, inflated_bytes: int, channels=("B", "G", "R")) -> Path:
    """A 16 x 16 float EXR whose one chunk inflates to ``inflated_bytes``."""
    header = _header(channels, (0, 0, 15, 15), (0, 0, 15, 15))
    data = _zeros_deflated(inflated_bytes)
    Path(path).write_bytes(_assemble(header, [struct.pack("<ii", 0, len(data)) + data]))
    return Path(path)


def display_window_exr(path, size: int, channels=("B", "G", "R")) -> Path:
    """A 4 x 4 data window inside a ``size`` x ``size`` display window."""
    header = _header(channels, (0, 0, 3, 3), (0, 0, size - 1, size - 1))
    data = _zeros_deflated(4 * 4 * 4 * len(channels))
    Path(path).write_bytes(_assemble(header, [struct.pack("<ii", 0, len(data)) + data]))
    return Path(path)


def huge_png(path, width: int, height: int) -> Path:
    """A PNG whose header claims ``width`` x ``height`` RGB8, with one tiny IDAT."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\0" * 1024)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return Path(path)


def huge_npy(path, height: int, width: int) -> Path:
    """A .npy whose header claims ``height`` x ``width`` float32 and holds 1 KB of data."""
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (%d, %d), }" % (height, width)
    header = header + " " * (63 - (len(header) + 10) % 64) + "\n"
    Path(path).write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode()
                           + b"\0" * 1024)
    return Path(path)
