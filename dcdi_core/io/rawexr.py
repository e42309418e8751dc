"""A small numpy-only reader and writer of scanline OpenEXR files.

Inside Blender the PyPI OpenImageIO clashes with Blender's own, a
distribution's Blender may have no OpenImageIO module at all, and Blender's
image API gives Python no access to a multilayer file's passes (only the
first). This module reads and writes EXR with numpy and the standard library
(``zlib``) only: the add-on reads Blender's multilayer renders with it, and
:mod:`dcdi_core.io.images` falls back on it when OpenImageIO does not import.

What it does:

* reads flat scanline files, single-part (Blender 3.x / 4.x multilayer) or
  multi-part (Blender 5 writes one part per pass), compressed with NONE,
  ZIPS (one scanline a chunk) or ZIP (16 scanlines a chunk); channels of
  type UINT, HALF or FLOAT, not subsampled. The pixels of anything else
  (tiled or deep parts, RLE, PIZ, PXR24, B44, DWA and other compressions)
  are refused by name (:class:`RawExrError`), as is a chunk that is
  truncated, corrupt or missing; their headers (windows, channels, string
  attributes) are read all the same;
* reads hostile files within bounds: every attribute this module uses is
  checked for its type and size, a header-only read stops at
  :data:`HEADER_MAX_BYTES`, a part whose data window holds more bytes than
  its chunks could inflate to is refused before anything is allocated
  (zlib expands at most :data:`ZLIB_MAX_RATIO`:1, NONE 1:1), and a chunk
  is inflated to at most one byte more than its scanlines hold;
* writes one-part scanline files (:func:`encode_exr`, :func:`write_exr`),
  HALF or FLOAT (or UINT) channels, compression NONE, ZIPS or ZIP. The bytes depend
  on the pixels and the options only (no time stamp, no host name), so the
  same pixels give the same bytes (with the same zlib).

Format facts used (OpenEXR "File Layout" and "Technical Introduction"): magic
20000630; a version word, 2 in its low byte, with flags 0x200 tiled, 0x400
long names (attribute and channel names up to 255 bytes rather than 31),
0x800 deep, 0x1000 multi-part. Each header is a list of (name, type name,
size, value) attributes ended by an empty name (a multi-part file's list of
headers ends with an empty header); a writer stores them sorted by name.
Then one offset table per part (``chunkCount`` entries, or one per block of
scanlines in a one-part file) of absolute uint64 file positions; then the
chunks: [part number (multi-part only)], the block's first y, the data's
byte count, the data. A block's raw data is, for each of its scanlines, for
each channel in name order, ``width`` little-endian samples (HALF 2 bytes,
FLOAT and UINT 4). ZIP and ZIPS transform the raw bytes before zlib: the
bytes at even positions, then those at odd positions (interleave), then each
byte replaced by its difference from the one before plus 128, modulo 256
(predictor; the first byte kept); a chunk whose compressed data would not be
smaller than its raw data is stored raw, and a reader tells the two apart by
the byte count.
"""
from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DcdiError

MAGIC = 20000630
_PIXEL_TYPES = {0: ("<u4", 4), 1: ("<f2", 2), 2: ("<f4", 4)}      # UINT, HALF, FLOAT
PIXEL_TYPE_NAMES = {0: "uint", 1: "half", 2: "float"}
_TYPE_OF_NAME = {v: k for k, v in PIXEL_TYPE_NAMES.items()}

#: compression code -> (name, scanlines per chunk)
COMPRESSIONS = {0: ("NONE", 1), 1: ("RLE", 1), 2: ("ZIPS", 1), 3: ("ZIP", 16), 4: ("PIZ", 32),
                5: ("PXR24", 16), 6: ("B44", 32), 7: ("B44A", 32), 8: ("DWAA", 32), 9: ("DWAB", 256)}
READ_COMPRESSIONS = (0, 2, 3)                       # NONE, ZIPS, ZIP
_CODE_OF_NAME = {"NONE": 0, "ZIPS": 2, "ZIP": 3}

_TILED, _LONG_NAMES, _DEEP, _MULTIPART = 0x200, 0x400, 0x800, 0x1000
_SHORT_NAME_MAX = 31
_STANDARD_ATTRIBUTES = ("channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
                        "screenWindowCenter", "screenWindowWidth", "name", "type", "chunkCount", "version", "tiles")
_LONG_NAME_MAX = 255
#: zlib level of the writer: on an undenoised factory frame (480 x 640 RGB
#: float32, 3.69 MB raw) levels 1 to 6 give 3.27-3.28 MB in 0.09-0.12 s.
ZIP_LEVEL = 4
_HEADER_PROBE = 1 << 20
#: a header-only read reads at most this much of the file (Blender's largest
#: multilayer headers are tens of KiB; a longer header is refused)
HEADER_MAX_BYTES = 16 << 20
#: deflate's largest expansion: a 258-byte match costs at least 2 bits
#: (RFC 1951), so n compressed bytes inflate to at most about 1032 n
ZLIB_MAX_RATIO = 1032
#: the standard attributes this module reads: name -> (type name, size in bytes, None: any)
_ATTRIBUTE_FORMS = {"channels": ("chlist", None), "compression": ("compression", 1), "dataWindow": ("box2i", 16),
                    "displayWindow": ("box2i", 16), "chunkCount": ("int", 4), "name": ("string", None),
                    "type": ("string", None)}
#: part types (the 'type' attribute) whose pixels this module reads; the others' headers only
_SCANLINE = "scanlineimage"
_PARALLEL_BYTES = 1 << 20         # files from this size on deflate their chunks on the thread pool


class RawExrError(DcdiError, ValueError):
    """An EXR file this module cannot read or write; the message names the
    file and why (``why``: the reason alone). A project error (DcdiError):
    every user-caused failure of this module's readers is one."""

    def __init__(self, path, why: str):
        self.path = str(path)
        self.why = why
        super().__init__(f"{path}: {why}")


# ------------------------------------------------------------------ the header
@dataclass(frozen=True)
class ExrChannel:
    name: str
    pixel_type: int                 # 0 UINT, 1 HALF, 2 FLOAT

    @property
    def type_name(self) -> str:
        return PIXEL_TYPE_NAMES[self.pixel_type]

    @property
    def nbytes(self) -> int:
        return _PIXEL_TYPES[self.pixel_type][1]


@dataclass(frozen=True)
class ExrPart:
    """One part's header: its channels in file (name) order, its windows
    (x0, y0, x1, y1 inclusive), its compression code and name ('' when the
    header has none), and where its offset table starts."""
    index: int
    name: str
    channels: tuple
    data_window: tuple
    display_window: tuple
    compression: int
    chunk_count: int
    strings: dict = field(default_factory=dict)     # the header's 'string' attributes {name: text}
    kind: str = _SCANLINE           # the part's type: scanlineimage, tiledimage, deepscanline, deeptile

    @property
    def width(self) -> int:
        return self.data_window[2] - self.data_window[0] + 1

    @property
    def height(self) -> int:
        return self.data_window[3] - self.data_window[1] + 1

    @property
    def compression_name(self) -> str:
        return COMPRESSIONS.get(self.compression, (f"code {self.compression}",))[0]

    @property
    def lines_per_chunk(self) -> int:
        return COMPRESSIONS.get(self.compression, ("", 1))[1]

    @property
    def label(self) -> str:
        return f"part {self.index} '{self.name}'" if self.name else f"part {self.index}"


def _cstr(buf: bytes, pos: int, path) -> tuple[str, int]:
    end = buf.find(b"\0", pos, pos + _LONG_NAME_MAX + 1)
    if end < 0:
        raise RawExrError(path, "truncated or damaged header (a name without its end)")
    return _text(buf[pos:end]), end + 1


def _text(raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _header(buf: bytes, pos: int, path) -> tuple[dict, int]:
    """Attributes from ``pos`` to the empty name; returns (attributes, next pos)."""
    attrs = {}
    while True:
        if pos >= len(buf):
            raise RawExrError(path, "truncated header")
        name, pos = _cstr(buf, pos, path)
        if not name:
            return attrs, pos
        typ, pos = _cstr(buf, pos, path)
        if pos + 4 > len(buf):
            raise RawExrError(path, "truncated header")
        (size,) = struct.unpack_from("<i", buf, pos)
        pos += 4
        if size < 0 or pos + size > len(buf):
            raise RawExrError(path, f"truncated or damaged header (attribute {name!r} of {size} bytes)")
        attrs[name] = (typ, buf[pos:pos + size])
        pos += size


def _channels(raw: bytes, path, label: str) -> tuple:
    out, pos = [], 0
    while pos < len(raw) and raw[pos] != 0:
        name, pos = _cstr(raw, pos, path)
        if pos + 16 > len(raw):
            raise RawExrError(path, f"{label}: damaged channel list")
        ptype = struct.unpack_from("<i", raw, pos)[0]
        xs, ys = struct.unpack_from("<ii", raw, pos + 8)
        if ptype not in _PIXEL_TYPES:
            raise RawExrError(path, f"{label}: channel {name!r} has pixel type {ptype} "
                                    "(allowed 0 UINT, 1 HALF, 2 FLOAT)")
        if (xs, ys) != (1, 1):
            raise RawExrError(path, f"{label}: channel {name!r} is subsampled ({xs}, {ys}); only (1, 1) is read")
        out.append(ExrChannel(name, ptype))
        pos += 16
    # stored in name order (byte order of the names) whatever the list says
    return tuple(sorted(out, key=lambda c: c.name.encode("utf-8")))


def _attribute(h: dict, key: str, path, label: str) -> bytes:
    """The value of standard attribute ``key``, refused unless of its type
    and size (:data:`_ATTRIBUTE_FORMS`): a damaged header must not reach a
    struct.unpack of the wrong size."""
    typ, raw = h[key]
    want, size = _ATTRIBUTE_FORMS[key]
    if typ != want or (size is not None and len(raw) != size):
        need = f"{want} of {size} bytes" if size is not None else want
        raise RawExrError(path, f"{label}: attribute {key!r} is {typ!r} of {len(raw)} bytes; allowed: {need}")
    return raw


def _box(h: dict, key: str, path, label: str) -> tuple:
    """A box2i attribute: (x0, y0, x1, y1), inclusive pixel coordinates."""
    return struct.unpack("<iiii", _attribute(h, key, path, label))


def _chunk_count(h: dict, path, label: str) -> int:
    """The 'chunkCount' attribute: the part's chunks (>= 1)."""
    (n,) = struct.unpack("<i", _attribute(h, "chunkCount", path, label))
    if n < 1:
        raise RawExrError(path, f"{label}: attribute 'chunkCount' = {n}; allowed: 1 .. {2 ** 31 - 1}")
    return n


def _part_kind(h: dict, flags: int, path, label: str) -> str:
    """The part's type: its 'type' attribute, else what the version flags say."""
    if "type" in h:
        return _text(_attribute(h, "type", path, label).rstrip(b"\0"))
    if flags & _DEEP:
        return "deeptile" if flags & _TILED else "deepscanline"
    return "tiledimage" if flags & _TILED else _SCANLINE


class ExrFile:
    """An EXR file's bytes and its parts' headers (:class:`ExrPart`), parsed
    once; :meth:`read` decodes a part's channels."""

    def __init__(self, path: str | os.PathLike, data: bytes | None = None, *, header_only: bool = False):
        """``header_only``: read the headers only (the first MiB of the file,
        up to :data:`HEADER_MAX_BYTES` if they are longer); :meth:`read` is
        then refused. Tiled and deep files' headers are read too."""
        self.path = Path(path)
        self.header_only = header_only
        if data is None:
            data = self._bytes(_HEADER_PROBE if header_only else None)
        self.buf = data
        try:
            self.parts, self._tables = self._parse(tables=not header_only)
        except RawExrError:
            if not (header_only and len(data) == _HEADER_PROBE):
                raise
            self.buf = self._bytes(HEADER_MAX_BYTES)
            try:
                self.parts, self._tables = self._parse(tables=False)
            except RawExrError as again:
                if len(self.buf) < HEADER_MAX_BYTES:
                    raise
                raise RawExrError(self.path, f"{again.why}; a header longer than {HEADER_MAX_BYTES >> 20} MiB "
                                             "is not read") from None

    def _bytes(self, n):
        try:
            with open(self.path, "rb") as f:
                return f.read() if n is None else f.read(n)
        except OSError as e:
            raise RawExrError(self.path, f"cannot read the file ({e.strerror})") from None

    def _parse(self, tables: bool = True):
        buf, path = self.buf, self.path
        if len(buf) < 8 or struct.unpack_from("<i", buf, 0)[0] != MAGIC:
            raise RawExrError(path, "not an OpenEXR file (bad magic number)")
        flags = struct.unpack_from("<I", buf, 4)[0]
        if flags & 0xFF != 2:
            raise RawExrError(path, f"OpenEXR format version {flags & 0xFF}; only version 2 is read")
        self.multipart = multi = bool(flags & _MULTIPART)
        headers, pos = self._headers(multi)
        parts = tuple(self._part(i, h, flags) for i, h in enumerate(headers))
        # a single-part tiled or deep file has no chunkCount to size its table
        # by: its headers are read, its pixels refused (read)
        if not tables or (not multi and parts[0].kind != _SCANLINE):
            self._chunks_start = None
            return parts, []
        out_tables = []
        for p in parts:
            if pos + 8 * p.chunk_count > len(buf):
                raise RawExrError(path, f"{p.label}: truncated offset table ({p.chunk_count} chunks)")
            out_tables.append(np.frombuffer(buf, "<u8", p.chunk_count, pos))
            pos += 8 * p.chunk_count
        self._chunks_start = pos
        return parts, out_tables

    def _headers(self, multi: bool) -> tuple[list, int]:
        """Every part's attributes {name: (type, bytes)}, and where the offset tables start."""
        buf, path, pos = self.buf, self.path, 8
        headers = []
        while True:
            h, pos = _header(buf, pos, path)
            headers.append(h)
            if not multi:
                return headers, pos
            if pos >= len(buf):
                raise RawExrError(path, "truncated header")
            if buf[pos] == 0:           # the empty header ends the list
                return headers, pos + 1

    def _part(self, i: int, h: dict, flags: int) -> ExrPart:
        """Part ``i``'s header, every attribute used checked for type and size."""
        path, label = self.path, f"part {i}"
        for key in ("channels", "compression", "dataWindow", "displayWindow"):
            if key not in h:
                raise RawExrError(path, f"{label} has no {key!r} attribute")
        name = _text(_attribute(h, "name", path, label).rstrip(b"\0")) if "name" in h else ""
        label = f"part {i} '{name}'" if name else label
        kind = _part_kind(h, flags, path, label)
        comp = _attribute(h, "compression", path, label)[0]
        dw, disp = _box(h, "dataWindow", path, label), _box(h, "displayWindow", path, label)
        ny, nx = dw[3] - dw[1] + 1, dw[2] - dw[0] + 1
        if ny < 1 or nx < 1:
            raise RawExrError(path, f"{label}: empty data window {dw}")
        n_chunks = -(-ny // COMPRESSIONS.get(comp, ("", 1))[1])
        if "chunkCount" in h:
            n_chunks = _chunk_count(h, path, label)
        elif self.multipart:
            raise RawExrError(path, f"{label} has no 'chunkCount' attribute")
        strings = {k: _text(v) for k, (t, v) in h.items() if t == "string"}
        channels = _channels(_attribute(h, "channels", path, label), path, label)
        return ExrPart(i, name, channels, dw, disp, comp, n_chunks, strings, kind)

    def _check_declared_bytes(self, p: ExrPart, declared: int) -> None:
        """Refuse, before allocating them, ``declared`` raw bytes of part ``p``
        that the file's chunks cannot hold: NONE stores them 1:1, zlib
        inflates at most :data:`ZLIB_MAX_RATIO`:1 (a damaged or hostile
        header: a 3 KB file declaring a 2 GB data window)."""
        held = max(0, len(self.buf) - self._chunks_start)
        ratio = 1 if p.compression == 0 else ZLIB_MAX_RATIO
        if declared > ratio * held:
            raise RawExrError(self.path, f"{p.label}: its data window ({p.width} x {p.height} px, "
                                         f"{len(p.channels)} channel(s)) holds {declared} bytes, but the file's "
                                         f"{held} bytes of chunks hold at most {ratio * held} ({p.compression_name}: "
                                         f"at most {ratio}:1): the header is damaged")

    def read(self, part: int = 0, names=None, *, raw_types: bool = False) -> dict[str, np.ndarray]:
        """{channel name: (H, W) array} of part ``part`` (the data window,
        rows top to bottom), ``names`` (default all) in file order. HALF and
        FLOAT come back float32; UINT as float32 too, unless ``raw_types``
        (then uint32). Raises RawExrError for what is not read (see the
        module's docstring) and for a damaged chunk."""
        if self.header_only:
            raise ValueError("ExrFile(header_only=True) reads no pixels")
        p = self.parts[part]
        path, buf = self.path, self.buf
        if p.kind != _SCANLINE:
            what = "deep" if p.kind.startswith("deep") else "tiled"
            raise RawExrError(path, f"{p.label} is a {what} image (type {p.kind!r}); only scanline images' pixels "
                                    "are read")
        if p.compression not in READ_COMPRESSIONS:
            raise RawExrError(path, f"{p.label} is compressed with {p.compression_name}; only NONE, ZIPS and ZIP "
                                    "are read without OpenImageIO")
        want = [c.name for c in p.channels] if names is None else list(names)
        missing = [n for n in want if n not in {c.name for c in p.channels}]
        if missing:
            raise RawExrError(path, f"{p.label} has no channel {missing[0]!r}")
        w, ny, y0 = p.width, p.height, p.data_window[1]
        line_bytes = sum(c.nbytes for c in p.channels) * w
        lines = p.lines_per_chunk
        n_blocks = -(-ny // lines)
        if len(self._tables[part]) != n_blocks:
            raise RawExrError(path, f"{p.label}: {len(self._tables[part])} chunks in the offset table, "
                                    f"expected {n_blocks} ({ny} scanlines, {lines} a chunk)")
        self._check_declared_bytes(p, ny * line_bytes)
        raw = np.empty((ny, line_bytes), np.uint8)
        seen = np.zeros(n_blocks, bool)
        head = 12 if self.multipart else 8
        for off in self._tables[part]:
            off = int(off)
            if off < self._chunks_start or off + head > len(buf):
                raise RawExrError(path, f"{p.label}: a chunk offset ({off}) outside the file: the file is "
                                        "truncated or damaged")
            if self.multipart and struct.unpack_from("<i", buf, off)[0] != part:
                raise RawExrError(path, f"{p.label}: the chunk at byte {off} belongs to another part")
            y, size = struct.unpack_from("<ii", buf, off + head - 8)
            block, rem = divmod(y - y0, lines)
            if rem or not 0 <= block < n_blocks or seen[block]:
                raise RawExrError(path, f"{p.label}: the chunk at byte {off} starts at scanline {y}, not at a "
                                        f"block of the data window (y {y0} .. {y0 + ny - 1}, {lines} lines a chunk)")
            seen[block] = True
            r0 = block * lines
            n_lines = min(lines, ny - r0)
            expect = n_lines * line_bytes
            if size < 0 or off + head + size > len(buf):
                raise RawExrError(path, f"{p.label}: the chunk at byte {off} (scanlines {y}..{y + n_lines - 1}) "
                                        f"runs past the end of the file: the file is truncated")
            data = buf[off + head:off + head + size]
            if p.compression == 0 or size == expect:        # stored raw (ZIP stores raw what zlib cannot shrink)
                if size != expect:
                    raise RawExrError(path, f"{p.label}: the chunk at byte {off} holds {size} bytes, expected "
                                            f"{expect} ({n_lines} uncompressed scanline(s))")
                block_bytes = np.frombuffer(data, np.uint8)
            else:
                block_bytes = _zip_decode(data, expect, path, f"{p.label}: the chunk at byte {off} "
                                                              f"(scanlines {y}..{y + n_lines - 1})")
            raw[r0:r0 + n_lines] = block_bytes.reshape(n_lines, line_bytes)
        if not seen.all():
            first = int(np.flatnonzero(~seen)[0]) * lines + y0
            raise RawExrError(path, f"{p.label}: no chunk for scanline {first}: the file is incomplete")
        out, at = {}, 0
        wanted = set(want)
        for c in p.channels:
            nb = c.nbytes * w
            if c.name in wanted:
                plane = np.ascontiguousarray(raw[:, at:at + nb]).view(_PIXEL_TYPES[c.pixel_type][0])
                plane = plane.reshape(ny, w)
                out[c.name] = plane.astype(np.uint32 if raw_types and c.pixel_type == 0 else np.float32)
            at += nb
        return out


def _zip_decode(data: bytes, expect: int, path, where: str) -> np.ndarray:
    """zlib, then the predictor and the interleave undone: the ``expect``
    raw bytes. Inflates at most one byte more than ``expect``, so a chunk
    that would inflate to gigabytes (a zlib bomb) costs ``expect`` bytes."""
    inflater = zlib.decompressobj()
    try:
        flat = inflater.decompress(data, expect + 1)
    except zlib.error as e:
        raise RawExrError(path, f"{where} is corrupt (zlib: {e})") from None
    if len(flat) > expect:
        raise RawExrError(path, f"{where} inflates to more than the {expect} bytes its scanlines hold: the file "
                                "is damaged")
    if len(flat) != expect or not inflater.eof:
        raise RawExrError(path, f"{where} decompresses to {len(flat)} bytes (the zlib stream "
                                f"{'ends' if inflater.eof else 'is cut short'}), expected {expect}: the file is "
                                "damaged")
    d = np.frombuffer(flat, np.uint8).copy()
    d[1:] -= np.uint8(128)                       # wraps modulo 256
    t = np.cumsum(d, dtype=np.uint8)             # t[i] = t[i-1] + d[i] - 128, modulo 256
    out = np.empty_like(t)
    half = (t.size + 1) // 2
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out


def _zip_encode(raw: np.ndarray, level: int) -> bytes:
    """The interleave and the predictor, then zlib (raw: 1-D uint8)."""
    t = np.concatenate([raw[0::2], raw[1::2]])
    d = np.empty_like(t)
    d[:1] = t[:1]
    d[1:] = t[1:] - t[:-1]                       # wraps modulo 256
    d[1:] += np.uint8(128)
    return zlib.compress(d.tobytes(), level)


# ------------------------------------------------------------------ reading, the add-on's way
def read_exr_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of a scanline EXR (NONE, ZIPS or ZIP) as (H, W) float32
    arrays, keyed by channel name (multi-part: parts' channels merged; a name
    that repeats is prefixed with the part's name). Rows are top to bottom."""
    f = ExrFile(path)
    out: dict[str, np.ndarray] = {}
    for p in f.parts:
        for c, a in f.read(p.index).items():
            out[f"{p.name}.{c}" if c in out else c] = a
    return out


# ------------------------------------------------------------------ writing
def _attr(name: str, typ: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(value)) + value


def encode_exr(channels: dict, *, pixel_type: str | dict = "float", compression: str = "ZIP",
               zip_level: int = ZIP_LEVEL, strings: dict | None = None, path="<memory>") -> bytes:
    """The bytes of a one-part scanline EXR holding ``channels`` ({name:
    (H, W) array}, all one shape; written in name order, as the format
    wants). ``pixel_type``: 'float' or 'half' (or 'uint', for unsigned
    integers) for every channel, or {name: type}; a value that a half cannot
    hold becomes inf, as a float16 cast makes it (callers check the range). ``compression``: 'ZIP' (16
    scanlines a chunk, the default), 'ZIPS' (one) or 'NONE'. Data and
    display window (0, 0) .. (W-1, H-1), increasing y, pixel aspect 1.
    ``strings``: extra header attributes of type string {name: text}."""
    if not channels:
        raise RawExrError(path, "no channel to write")
    comp = _CODE_OF_NAME.get(str(compression).upper())
    if comp is None:
        raise RawExrError(path, f"compression {compression!r}: only NONE, ZIPS and ZIP are written")
    names = sorted(channels, key=lambda n: n.encode("utf-8"))
    shape = np.shape(channels[names[0]])
    if len(shape) != 2 or shape[0] < 1 or shape[1] < 1:
        raise RawExrError(path, f"channel {names[0]!r}: an (H, W) array is needed, got shape {shape}")
    h, w = shape
    planes, ptypes, long_names = [], [], False
    for n in names:
        a = np.asarray(channels[n])
        if a.shape != shape:
            raise RawExrError(path, f"channel {n!r} has shape {a.shape}, channel {names[0]!r} {shape}")
        t = pixel_type.get(n, "float") if isinstance(pixel_type, dict) else pixel_type
        if t not in ("float", "half", "uint"):
            raise RawExrError(path, f"channel {n!r}: pixel type {t!r} (allowed float, half, uint)")
        code = _TYPE_OF_NAME[t]
        if not n or "\0" in n or len(n.encode("utf-8")) > _LONG_NAME_MAX:
            raise RawExrError(path, f"channel name {n!r}: 1 to {_LONG_NAME_MAX} bytes, no NUL")
        long_names |= len(n.encode("utf-8")) > _SHORT_NAME_MAX
        with np.errstate(over="ignore"):
            planes.append(np.ascontiguousarray(a, _PIXEL_TYPES[code][0]).view(np.uint8).reshape(h, -1))
        ptypes.append(code)
    rows = planes[0] if len(planes) == 1 else np.concatenate(planes, axis=1)     # (H, line bytes)
    chlist = b"".join(n.encode("utf-8") + b"\0" + struct.pack("<iB3xii", t, 0, 1, 1)
                      for n, t in zip(names, ptypes)) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    extra = []
    for key, text in sorted((strings or {}).items()):
        if not key or "\0" in key or len(key.encode("utf-8")) > _SHORT_NAME_MAX or key in _STANDARD_ATTRIBUTES:
            raise RawExrError(path, f"header attribute {key!r}: 1 to {_SHORT_NAME_MAX} bytes, no NUL, not a "
                                    "standard attribute")
        extra.append(_attr(key, "string", str(text).encode("utf-8")))
    header = b"".join(sorted(extra + [
        _attr("channels", "chlist", chlist),
        _attr("compression", "compression", bytes([comp])),
        _attr("dataWindow", "box2i", box),
        _attr("displayWindow", "box2i", box),
        _attr("lineOrder", "lineOrder", b"\0"),
        _attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        _attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        _attr("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ])) + b"\0"
    lines = COMPRESSIONS[comp][1]
    starts = range(0, h, lines)
    blocks = [rows[y:y + lines].reshape(-1) for y in starts]
    packed = [None] * len(blocks)
    if comp != 0:
        packed = _each(lambda b: _zip_encode(b, zip_level), blocks, parallel=rows.nbytes >= _PARALLEL_BYTES)
    chunks = []
    for y, block, pack in zip(starts, blocks, packed):
        data = block.tobytes()
        if pack is not None and len(pack) < len(data):
            data = pack
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    version = struct.pack("<iI", MAGIC, 2 | (_LONG_NAMES if long_names else 0))
    pos = len(version) + len(header) + 8 * len(chunks)
    offsets = []
    for c in chunks:
        offsets.append(pos)
        pos += len(c)
    return version + header + np.asarray(offsets, "<u8").tobytes() + b"".join(chunks)


def _each(fn, items, *, parallel: bool) -> list:
    """[fn(x) for x in items], on the shared thread pool when ``parallel``
    (zlib lets go of the GIL: a 480 x 640 RGB frame deflates in 0.1 s on one
    core) and the caller is not itself one of its threads."""
    import threading
    if not parallel or len(items) < 2 or threading.current_thread().name.startswith("dcdi"):
        return [fn(x) for x in items]
    from ..parallel import thread_pool, workers
    if workers() < 2:
        return [fn(x) for x in items]
    return list(thread_pool().map(fn, items))


def write_exr(path: str | os.PathLike, channels: dict, **options) -> None:
    """:func:`encode_exr` written to ``path`` (not atomically: callers that
    need that write to a temporary, as dcdi_core.io.images does)."""
    data = encode_exr(channels, path=path, **options)
    try:
        Path(path).write_bytes(data)
    except OSError as e:
        raise RawExrError(path, f"cannot be written ({e.strerror})") from None
