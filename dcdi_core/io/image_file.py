"""What an image or depth file holds, from its header: its parts and their
channels, opened through OpenImageIO where it imports and through dcdi's own
EXR reader (:mod:`dcdi_core.io.rawexr`) where it does not, presented alike
(OpenImageIO's channel order, its spec's windows); which channels are the
colour and which the depth; a ``.npy`` depth map's header. Nothing here
reads more than a header but ``_read_channels`` and ``_raw_read_channels``,
which the readers of :mod:`dcdi_core.io.images` call once
:mod:`dcdi_core.io.image_checks` has bounded the read.

A path that is not a regular file (a pipe, a device: a read would block
for ever or never end) is refused before it is opened (``_check_file``).
The helpers with a leading underscore are shared by the image modules of
``dcdi_core.io`` only.
"""
from __future__ import annotations

import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import rawexr
from ..errors import DcdiError

__all__ = ["ImageFileError", "DEPTH_CHANNELS", "NO_OPENIMAGEIO", "have_openimageio"]

#: Depth channel names tried in this order (in every part of the file) when
#: :func:`~dcdi_core.io.images.read_depth` is not told which channel to use.
DEPTH_CHANNELS = ("Z", "depth.Z", "Depth.V", "V", "depth", "R", "Y")

# Names of layers (the part of "ViewLayer.Combined.R" before ".R") preferred
# when a file holds several RGB layers and no plain R, G, B channels.
_PREFERRED_LAYERS = ("combined", "image", "rgba", "beauty")

# OpenImageIO format names whose pixel values are linear light whatever their
# storage type.
_LINEAR_FORMATS = ("openexr", "hdr")

_MAX_LISTED_CHANNELS = 24


class ImageFileError(DcdiError, ValueError):
    """An image or depth file that cannot be read or written as asked.

    ``path`` is the file; the message says what is wrong with it (and which
    channel or part, where that matters).
    """

    def __init__(self, path, message):
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")



#: what to do when a file needs OpenImageIO and it does not import
NO_OPENIMAGEIO = ("install OpenImageIO (pip install OpenImageIO; for a distribution's Blender, its "
                  "python3-openimageio package)")


def _oiio():
    """The OpenImageIO module, or None where it does not import (then EXR
    goes through :mod:`rawexr`). Imported on every call (a cached module is
    cheap), so that blocking it (``sys.modules['OpenImageIO'] = None``)
    takes effect at once."""
    try:
        import OpenImageIO as oiio
    except ImportError:
        return None
    return oiio


def have_openimageio() -> bool:
    """Whether OpenImageIO imports (else only EXR and .npy files are read and written)."""
    return _oiio() is not None


@dataclass(frozen=True)
class _Part:
    index: int          # OpenImageIO subimage number = EXR part number
    name: str           # EXR part name ('' when the file has none)
    channels: tuple     # channel names in OpenImageIO's order
    spec: object        # OpenImageIO.ImageSpec of the part

    @property
    def label(self):
        return f"part {self.index} '{self.name}'" if self.name else f"part {self.index}"

    def qualified(self, i):
        """Channel ``i``'s name prefixed with the part name (once)."""
        n = self.channels[i]
        if not self.name or n.startswith(self.name + "."):
            return n
        return f"{self.name}.{n}"


def _check_file(path: Path):
    if not path.exists():
        raise ImageFileError(path, "file not found")
    if path.is_dir():
        raise ImageFileError(path, "is a folder, not an image file")
    if not path.is_file():          # a FIFO would block the read for ever, a device never end
        raise ImageFileError(path, "is not a regular file (a pipe or a device); give an image file")


def _open(path: Path, oiio):
    _check_file(path)
    config = oiio.ImageSpec()
    # PNG: keep colour as stored instead of multiplying it by alpha.
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _held_stderr() as held:
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            why = _said(oiio.geterror(), held) or "unknown format"
            raise ImageFileError(path, f"cannot be read as an image ({why})")
    return inp


def _one_line(text: str) -> str:
    """OpenImageIO's error text (several lines for one error) on one line."""
    return " ".join(str(text).split())


class _Held:
    """What the C libraries wrote to standard error (:func:`_held_stderr`)."""
    file = None

    def text(self) -> str:
        if self.file is None:
            return ""
        self.file.seek(0)
        return self.file.read().decode("utf-8", "replace")


@contextmanager
def _held_stderr():
    """Hold what C libraries write to the process's standard error while
    OpenImageIO works (OpenEXR's and libpng's own lines about a damaged
    file), so that the file's refusal is one line: an ImageFileError drops
    it (its message says it, :func:`_said`), anything else writes it back.
    Only in the main thread (the dcdi command's): file descriptor 2 is the
    process's, and redirections from two threads could interleave."""
    held = _Held()
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield held
        return
    with tempfile.TemporaryFile() as held.file:
        os.dup2(held.file.fileno(), 2)
        refused = False
        try:
            yield held
        except ImageFileError:
            refused = True
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            text = held.text()
            if text and not refused:
                os.write(2, text.encode("utf-8", "replace"))


def _said(message: str, held: _Held) -> str:
    """OpenImageIO's error ``message`` on one line, followed by what the C
    libraries wrote meanwhile where it adds to it (OpenEXR says why a chunk
    is damaged; OpenImageIO relays less), at most 400 characters."""
    text = _one_line(message)
    for line in held.text().splitlines():
        said = _one_line(line.split(": ", 1)[-1])          # without the file's name the library puts first
        if said and said not in text:
            text = f"{text}; {said}" if text else said
    return text if len(text) <= 400 else text[:400] + "..."


def _parts(inp, path):
    parts = []
    s = 0
    while inp.seek_subimage(s, 0):
        spec = inp.spec(s, 0)
        try:                        # OpenImageIO's binding decodes names as UTF-8
            name = spec.getattribute("oiio:subimagename") or ""
            channels = tuple(spec.channelnames)
        except UnicodeDecodeError as e:
            raise ImageFileError(path, f"part {s}: a part or channel name is not UTF-8 text ({e.reason} at byte "
                                       f"{e.start}): a damaged header?") from None
        parts.append(_Part(s, str(name), channels, spec))
        s += 1
    if not parts:
        raise ImageFileError(path, "contains no image")
    return parts


def _describe(parts):
    def chans(p):
        names = list(p.channels)
        if len(names) > _MAX_LISTED_CHANNELS:
            names = names[:_MAX_LISTED_CHANNELS] + [f"... ({len(p.channels)} in all)"]
        return ", ".join(names) if names else "(none)"

    if len(parts) == 1:
        return f"channels found: {chans(parts[0])}"
    return "channels found: " + "; ".join(f"{p.label}: {chans(p)}" for p in parts)


def _read_channels(inp, part, indices, path):
    """Pixels of the given channels of one part, (h, w, len(indices)) float32."""
    lo, hi = min(indices), max(indices) + 1
    # Always the explicit (subimage, miplevel, chbegin, chend) form: in the
    # OpenImageIO 3.0 Python binding, read_image(chbegin, chend, format) after
    # seek_subimage() reads the wrong subimage or crashes.
    with _held_stderr() as held:
        data = inp.read_image(part.index, 0, lo, hi, "float")
        if data is None:
            raise ImageFileError(path, f"pixels of {part.label} cannot be read ({_said(inp.geterror(), held)})")
    data = np.asarray(data, dtype=np.float32)
    if data.ndim == 2:
        data = data[..., None]
    return data[..., [i - lo for i in indices]]


# ---- without OpenImageIO: EXR through rawexr, presented as OpenImageIO presents it

# OpenImageIO's canonical channel order (its EXR reader; checked on 3.0 and 3.1): the
# channels sorted by layer (the name up to its last dot), then within a layer
# by these suffixes (ignoring case), then by name; a layer holding X and Y or
# Z (a normal, a position) takes the second list
_OIIO_SPECIAL = ("r", "red", "g", "green", "b", "blue", "y", "real", "imag", "a", "alpha", "ar", "ra", "ag",
                 "ga", "ab", "ba", "z", "depth", "zback")
_OIIO_SPECIAL_XYZ = ("r", "red", "g", "green", "b", "blue", "x", "y", "z", "real", "imag", "a", "alpha", "ar",
                     "ra", "ag", "ga", "ab", "ba", "depth", "zback")


def _split_layer(name: str) -> tuple[str, str]:
    dot = name.rfind(".")
    return (name[:dot + 1], name[dot + 1:]) if dot >= 0 else ("", name)


def _oiio_channel_order(names) -> list:
    """``names`` in the order OpenImageIO presents an EXR part's channels."""
    layers: dict[str, set] = {}
    for n in names:
        layer, suffix = _split_layer(n)
        layers.setdefault(layer, set()).add(suffix.lower())

    def key(n):
        layer, suffix = _split_layer(n)
        got = layers[layer]
        table = _OIIO_SPECIAL_XYZ if "x" in got and ("y" in got or "z" in got) else _OIIO_SPECIAL
        low = suffix.lower()
        return layer.encode("utf-8"), table.index(low) if low in table else 10000, suffix.encode("utf-8")

    return sorted(names, key=key)


@dataclass(frozen=True)
class _RawSpec:
    """The part of an OpenImageIO ImageSpec this module uses, for a part read by rawexr."""
    x: int
    y: int
    width: int
    height: int
    full_x: int
    full_y: int
    full_width: int
    full_height: int
    types: tuple            # rawexr pixel type per channel, in the part's (OpenImageIO) order
    alpha_channel: int = -1


_IMAGE_MAGIC = ((b"\x89PNG", "a PNG file"), (b"\xff\xd8", "a JPEG file"), (b"II*\0", "a TIFF file"),
                (b"MM\0*", "a TIFF file"), (b"#?RADIANCE", "a Radiance HDR file"), (b"#?RGBE", "a Radiance HDR file"))


def _kind_of(path: Path) -> str:
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as e:
        raise ImageFileError(path, f"cannot be read ({e.strerror})") from None
    for magic, kind in _IMAGE_MAGIC:
        if head.startswith(magic):
            return kind
    if len(head) >= 4 and int.from_bytes(head[:4], "little") == rawexr.MAGIC:
        return "exr"
    return "not an image file this reader knows"


def _raw_exr(path: Path, header_only: bool = False):
    """(rawexr.ExrFile, parts as _Part) of an EXR file, without OpenImageIO."""
    _check_file(path)
    kind = _kind_of(path)
    if kind != "exr":
        raise ImageFileError(path, f"cannot be read without OpenImageIO ({kind}; only OpenEXR files are read "
                                   f"by dcdi's own reader): {NO_OPENIMAGEIO}, or convert it to EXR")
    try:
        f = rawexr.ExrFile(path, header_only=header_only)
    except rawexr.RawExrError as e:
        raise ImageFileError(path, f"cannot be read as an EXR ({e.why})") from None
    parts = []
    for p in f.parts:
        suffixes = sorted(_split_layer(c.name)[1].lower() for c in p.channels)
        if suffixes in (["by", "ry", "y"], ["a", "by", "ry", "y"], ["alpha", "by", "ry", "y"]):
            raise ImageFileError(path, f"{p.label} is a luminance-chroma EXR (Y, RY, BY), which dcdi's own EXR "
                                       f"reader does not convert to RGB: {NO_OPENIMAGEIO}")
        by_name = {c.name: c for c in p.channels}
        chans = [by_name[n] for n in _oiio_channel_order(by_name)]
        (x0, y0, x1, y1), (d0, e0, d1, e1) = p.data_window, p.display_window
        alpha = next((i for i, c in enumerate(chans) if c.name.rsplit(".", 1)[-1].lower() in ("a", "alpha")), -1)
        spec = _RawSpec(x0, y0, x1 - x0 + 1, y1 - y0 + 1, d0, e0, d1 - d0 + 1, e1 - e0 + 1,
                        tuple(c.pixel_type for c in chans), alpha)
        parts.append(_Part(p.index, p.name, tuple(c.name for c in chans), spec))
    return f, parts


def _raw_read_channels(f, part, indices, path, *, normalise_uint=True):
    """Pixels of the given channels of one part, (h, w, len(indices)) float32,
    as OpenImageIO's read_image(..., "float") gives them (UINT normalised by
    2^32 - 1)."""
    names = [part.channels[i] for i in indices]
    try:
        planes = f.read(part.index, names, raw_types=True)
    except rawexr.RawExrError as e:
        raise ImageFileError(path, f"pixels of {part.label} cannot be read without OpenImageIO ({e.why}); "
                                   f"{NO_OPENIMAGEIO}, or write it as a scanline EXR, uncompressed or ZIP-compressed") from None
    out = []
    for n in names:
        a = planes[n]
        if a.dtype == np.uint32:
            a = (a.astype(np.float64) / 4294967295.0).astype(np.float32) if normalise_uint else a.astype(np.float32)
        out.append(a)
    return np.stack(out, axis=-1)


def _find(names, wanted):
    """Index of ``wanted`` in ``names``, exact first, then ignoring case."""
    if wanted in names:
        return names.index(wanted)
    low = [n.lower() for n in names]
    return low.index(wanted.lower()) if wanted.lower() in low else None


def _rgb_indices(names):
    idx = [_find(names, c) for c in "RGB"]
    return None if None in idx else idx


def _layer_rgb_indices(names):
    """R, G, B of a layer such as 'ViewLayer.Combined.(R|G|B)'."""
    layers = [n[:-2] for n in names
              if n.endswith(".R") and n[:-2] + ".G" in names and n[:-2] + ".B" in names]
    if not layers:
        return None
    layer = min(layers, key=lambda p: p.rsplit(".", 1)[-1].lower() not in _PREFERRED_LAYERS)
    return [names.index(f"{layer}.{c}") for c in "RGB"]


def _choose_colour(parts, fmt, path):
    """(part, channel indices): three for colour, one for grey."""
    for finder in (_rgb_indices, _layer_rgb_indices):
        for part in parts:
            idx = finder(part.channels)
            if idx:
                return part, idx
    for part in parts:
        i = _find(part.channels, "Y")
        if i is not None:
            return part, [i]
    if fmt not in _LINEAR_FORMATS:  # formats whose channels are positional
        part = parts[0]
        n = len(part.channels)
        alpha = part.spec.alpha_channel
        if n == 1 or (n == 2 and alpha == 1):
            return part, [0]
        if n == 3 or (n == 4 and alpha == 3):
            return part, [0, 1, 2]
    raise ImageFileError(
        path, f"no colour channels to read (need R, G, B, a layer's .R/.G/.B, or one grey channel Y); "
              f"{_describe(parts)}")


def _is_float(typedesc):
    oiio = _oiio()
    return typedesc.basetype in (oiio.BASETYPE.FLOAT, oiio.BASETYPE.HALF, oiio.BASETYPE.DOUBLE)


def _choose_depth(parts, channel, path):
    wanted = (channel,) if channel is not None else DEPTH_CHANNELS

    def pick(name, matches):
        if len(matches) > 1:
            found = ", ".join(f"'{p.qualified(i)}' ({p.label})" for p, i in matches)
            raise ImageFileError(
                path, f"several channels match depth channel '{name}': {found}; "
                      f"choose one as '<part>.<channel>' (--depth-channel in the dcdi command, channel= in read_depth)")
        return matches[0] if matches else None

    # 1. exact channel names, in order of preference, across every part
    for name in wanted:
        hit = pick(name, [(p, i) for p in parts for i, n in enumerate(p.channels) if n == name])
        if hit:
            return hit
    # 2. ignoring case, with a part or layer prefix ('ViewLayer.Depth.Z' for
    #    'depth.Z', part 'depth' + channel 'Z' for 'depth.Z'); undotted names
    #    only match whole channel names, so 'Z' never takes 'Normal.Z'.
    for name in wanted:
        low = name.lower()
        matches = []
        for p in parts:
            for i, n in enumerate(p.channels):
                q = p.qualified(i).lower()
                if n.lower() == low or q == low or ("." in name and q.endswith("." + low)):
                    matches.append((p, i))
        hit = pick(name, matches)
        if hit:
            return hit
    if channel is not None:
        raise ImageFileError(path, f"no channel '{channel}'; {_describe(parts)}")
    raise ImageFileError(
        path, f"no depth channel found (looked for {', '.join(DEPTH_CHANNELS)} in every part); "
              f"{_describe(parts)}; choose one (--depth-channel in the dcdi command, channel= in read_depth)")


def _npy_header(path: Path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of a .npy depth map from its header alone, refused
    unless a 2-D (or H x W x 1) array of real numbers whose bytes the file
    holds: a damaged header must not make np.load allocate its shape."""
    if not path.exists():
        raise ImageFileError(path, "file not found")
    _check_file(path)
    fmt = np.lib.format
    try:
        with open(path, "rb") as f:
            version = fmt.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"format version {version[0]}.{version[1]}; 1.0 and 2.0 are read")
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read(f)
            held = os.fstat(f.fileno()).st_size - f.tell()
    except (OSError, ValueError, TypeError, SyntaxError) as exc:
        raise ImageFileError(path, f"cannot be read as a .npy array ({_one_line(exc)})") from None
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] != 1) or min(shape) < 1:
        raise ImageFileError(path, f"a depth map must be a 2-D (H, W) array; got shape {shape}")
    if dtype.kind not in "fiu":
        raise ImageFileError(path, f"a depth map must hold real numbers (metres); got dtype {dtype}")
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if declared > held:
        raise ImageFileError(path, f"its header declares a {' x '.join(map(str, shape))} array of {dtype} "
                                   f"({declared} bytes) but the file holds {held}: truncated or damaged")
    return tuple(shape[:2]), dtype


def _oiio_header(path: Path, oiio):
    """(parts, format name) of a file, from its header through OpenImageIO."""
    inp = _open(path, oiio)
    try:
        return _parts(inp, path), inp.format_name()
    finally:
        inp.close()


def _colour_part(parts, fmt, path, strict: bool):
    """The part :func:`~dcdi_core.io.images.read_image` reads; where none holds colour, the first
    (its size is still the file's), unless ``strict``."""
    try:
        return _choose_colour(parts, fmt, path)[0]
    except ImageFileError:
        if strict:
            raise
        return parts[0]
