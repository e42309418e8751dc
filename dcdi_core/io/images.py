"""Read and write images and depth maps in the project's conventions.

In memory an image is float32 ``(H, W, 3)`` linear light and a depth map is
float32 ``(H, W)`` in metres, planar (docs/design.md "Conventions"; NaN, 0 or a
negative depth marks an invalid pixel, ``inf`` or Blender's 1e10 infinity;
this module stores depths exactly as they are and leaves that reading to the
caller).

On disk:

* EXR, Radiance HDR and floating-point TIFF hold linear values and are read as
  stored; PNG, JPEG and 8- or 16-bit TIFF are taken to be sRGB-encoded and are
  decoded with the exact (piecewise) sRGB curve.
* A grey image becomes three equal channels; an alpha channel is dropped
  (PNG alpha is read unassociated, so the colour is not multiplied by it).
* Multi-part EXR files (Blender 5 writes multi-layer passes as separate parts)
  are searched part by part, for the colour and for the depth channel.
* Every write goes to a temporary file beside the target and is renamed onto
  it only once complete, so a failed write never leaves a half-written file.
  A non-finite value is never written to an image: it raises
  :class:`ImageFileError`.

OpenImageIO (``import OpenImageIO``) does the file work when it imports; it is
imported lazily, inside the functions, so that ``dcdi_core`` imports without
it. Where it does not import (a distribution's Blender without its
OpenImageIO package, or a Python where it is blocked), EXR files and ``.npy``
depth maps are read and written by the project's own numpy EXR code,
:mod:`dcdi_core.io.rawexr`, with the same rules (the colour and depth
channel choice, the data and display windows, the finite check, the atomic
write): scanline EXR compressed with NONE, ZIPS or ZIP is read, ZIP-compressed
EXR is written (float32 or half, like OpenImageIO's). What it cannot do (PNG,
JPEG, TIFF, HDR; EXR with PIZ or another compression) is refused by
:class:`ImageFileError` in one line naming the file and what to install.
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
from .. import memory
from ..atomic import atomic_path
from ..errors import DcdiError

__all__ = [
    "ImageFileError",
    "DEPTH_CHANNELS",
    "read_image",
    "write_image",
    "read_depth",
    "write_depth",
    "srgb_to_linear",
    "linear_to_srgb",
    "have_openimageio",
    "image_size",
    "depth_size",
    "check_job_inputs",
]

#: Depth channel names tried in this order (in every part of the file) when
#: :func:`read_depth` is not told which channel to use.
DEPTH_CHANNELS = ("Z", "depth.Z", "Depth.V", "V", "depth", "R", "Y")

# Names of layers (the part of "ViewLayer.Combined.R" before ".R") preferred
# when a file holds several RGB layers and no plain R, G, B channels.
_PREFERRED_LAYERS = ("combined", "image", "rgba", "beauty")

# OpenImageIO format names whose pixel values are linear light whatever their
# storage type.
_LINEAR_FORMATS = ("openexr", "hdr")

# extension -> (OpenImageIO format name, allowed bit depths, default bit depth)
_WRITE_FORMATS = {
    ".exr": ("openexr", (32, 16), 32),
    ".png": ("png", (8, 16), 8),
    ".jpg": ("jpeg", (8,), 8),
    ".jpeg": ("jpeg", (8,), 8),
}

_HALF_MAX = 65504.0
_MAX_LISTED_CHANNELS = 24

#: a display window may pad its data window up to this many pixels (an
#: 8192 x 8192 frame), and beyond that up to DISPLAY_PAD_FACTOR times the
#: data window: 4 x 4 pixels in a 20000 x 20000 display window (a 3 KB
#: file) would otherwise allocate 4.8 GB of padding
DISPLAY_PAD_MAX_PX = 1 << 26
DISPLAY_PAD_FACTOR = 4
# Bytes held while a part is read, for the memory guard: per sample (pixel x
# channel read) of the data window the decoded float32 and its channel
# selection (8) and the sRGB decode's float64 temporaries (48); per pixel
# of a display window, the placed float32 RGB and its contiguous copy.
_READ_BYTES_PER_SAMPLE = 56
_PLACE_BYTES_PER_PX = 24


class ImageFileError(DcdiError, ValueError):
    """An image or depth file that cannot be read or written as asked.

    ``path`` is the file; the message says what is wrong with it (and which
    channel or part, where that matters).
    """

    def __init__(self, path, message):
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


# --------------------------------------------------------------------------
# sRGB transfer functions
# --------------------------------------------------------------------------

def _float_result(x):
    a = np.asarray(x)
    dtype = np.result_type(a.dtype, np.float32) if a.dtype.kind in "fiub" else np.float64
    return a.astype(np.float64), dtype


def _finish(out, dtype):
    out = out.astype(dtype, copy=False)
    return out[()] if out.ndim == 0 else out


def srgb_to_linear(x):
    """The exact sRGB EOTF (IEC 61966-2-1), elementwise.

    ``x / 12.92`` up to 0.04045, ``((x + 0.055) / 1.055) ** 2.4`` above; the
    linear segment continues below 0 and the power segment above 1. float32 in,
    float32 out (float64 for float64 input); NaN stays NaN.
    """
    v, dtype = _float_result(x)
    out = np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)
    return _finish(out, dtype)


def linear_to_srgb(x):
    """The exact inverse of :func:`srgb_to_linear`, elementwise.

    ``12.92 * x`` up to 0.0031308, ``1.055 * x ** (1 / 2.4) - 0.055`` above.
    """
    v, dtype = _float_result(x)
    out = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.maximum(v, 0.0031308) ** (1.0 / 2.4) - 0.055)
    return _finish(out, dtype)


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------

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


def _displayed(spec) -> bool:
    """Whether the readers return the display window (EXR may differ from
    the data window) rather than the data window itself."""
    same = (spec.x, spec.y, spec.width, spec.height) == (spec.full_x, spec.full_y, spec.full_width, spec.full_height)
    return not same and spec.full_width > 0 and spec.full_height > 0


def _returned_size(spec) -> tuple[int, int]:
    """(height, width) px of what the readers return for a part: the
    display window where :func:`_to_display_window` places the data in it,
    else the data window."""
    return (spec.full_height, spec.full_width) if _displayed(spec) else (spec.height, spec.width)


def _check_read(path, part, n_channels: int) -> None:
    """Refuse, before a pixel is read, a part whose reading cannot be done
    within bounds: a display window absurdly larger than its data window
    (:data:`DISPLAY_PAD_MAX_PX`, :data:`DISPLAY_PAD_FACTOR`), or bytes the
    memory guard refuses (``n_channels`` read, :data:`_READ_BYTES_PER_SAMPLE`;
    rawexr also decodes every channel of the part: their stored bytes)."""
    spec = part.spec
    h, w = spec.height, spec.width
    fh, fw = _returned_size(spec)
    shown = fh * fw if _displayed(spec) else 0
    if shown > max(DISPLAY_PAD_MAX_PX, DISPLAY_PAD_FACTOR * h * w):
        raise ImageFileError(path, f"{part.label}: display window {fw} x {fh} px around a data window of {w} x {h} "
                                   f"px; a display window over {DISPLAY_PAD_MAX_PX} px may be at most "
                                   f"{DISPLAY_PAD_FACTOR} times its data window (a damaged header?)")
    stored = sum(2 if t == 1 else 4 for t in spec.types) if isinstance(spec, _RawSpec) else 0
    need = h * w * (n_channels * _READ_BYTES_PER_SAMPLE + stored) + shown * _PLACE_BYTES_PER_PX
    memory.check_fits(need, f"{path}: reading {part.label} ({w} x {h} px, {n_channels} channel(s), returned as "
                            f"{fw} x {fh} px)", "use a smaller image (or crop it into parts)")


def _to_display_window(data, spec, fill):
    """Place the data window's pixels in the display window (EXR may differ)."""
    x, y, w, h = spec.x, spec.y, spec.width, spec.height
    fx, fy, fw, fh = spec.full_x, spec.full_y, spec.full_width, spec.full_height
    if not _displayed(spec):
        return data
    out = np.full((fh, fw, data.shape[2]), fill, dtype=np.float32)
    x0, x1 = max(x, fx), min(x + w, fx + fw)
    y0, y1 = max(y, fy), min(y + h, fy + fh)
    if x0 < x1 and y0 < y1:
        out[y0 - fy:y1 - fy, x0 - fx:x1 - fx] = data[y0 - y:y1 - y, x0 - x:x1 - x]
    return out


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


def read_image(path) -> np.ndarray:
    """Read an image file as float32 ``(H, W, 3)`` linear light.

    EXR, HDR and floating-point TIFF values are returned as stored; 8- and
    16-bit files (PNG, JPEG, TIFF) are decoded from sRGB. In an EXR the colour
    is the first part holding R, G and B (else a layer's ``<layer>.R/G/B``,
    preferring a 'Combined' layer, else a grey Y channel). Raises
    :class:`ImageFileError` naming the file when it is missing, unreadable or
    has no usable colour channels.
    """
    path = Path(path)
    oiio = _oiio()
    if oiio is None:
        f, parts = _raw_exr(path)
        part, indices = _choose_colour(parts, "openexr", path)
        _check_read(path, part, len(indices))
        data = _to_display_window(_raw_read_channels(f, part, indices, path), part.spec, 0.0)
        if data.shape[2] == 1:
            data = np.repeat(data, 3, axis=2)
        return np.ascontiguousarray(data, dtype=np.float32)
    inp = _open(path, oiio)
    try:
        parts = _parts(inp, path)
        fmt = inp.format_name()
        part, indices = _choose_colour(parts, fmt, path)
        _check_read(path, part, max(indices) - min(indices) + 1)
        data = _read_channels(inp, part, indices, path)
    finally:
        inp.close()
    if not (fmt in _LINEAR_FORMATS or _is_float(part.spec.format)):
        data = srgb_to_linear(data)
    data = _to_display_window(data, part.spec, 0.0)
    if data.shape[2] == 1:
        data = np.repeat(data, 3, axis=2)
    return np.ascontiguousarray(data, dtype=np.float32)


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


def _read_depth_npy(path: Path):
    (h, w), dtype = _npy_header(path)
    memory.check_fits(h * w * (dtype.itemsize + 8), f"{path}: reading a {w} x {h} px depth map",
                      "use a smaller depth map")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ImageFileError(path, f"cannot be read as a .npy array ({exc})") from exc
    return _as_depth(arr, path)


def _as_depth(arr, path):
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise ImageFileError(path, f"a depth map must be a 2-D (H, W) array; got shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise ImageFileError(path, f"a depth map must hold real numbers (metres); got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def read_depth(path, *, channel=None) -> np.ndarray:
    """Read a depth map as float32 ``(H, W)`` metres from an EXR (or ``.npy``).

    The channel is ``channel`` when given (a channel name, or
    ``'<part>.<channel>'``), else the first of :data:`DEPTH_CHANNELS` found,
    searching every part of a multi-part EXR; a layer prefix is allowed
    (Blender's 'ViewLayer.Depth.Z' matches 'depth.Z'). Values come back as
    stored: inf, 1e10, NaN, 0 and negatives are kept for the caller to
    interpret. Pixels outside an EXR's data window are NaN (invalid).
    Integer-valued image files are refused: they cannot hold metres.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        return _read_depth_npy(path)
    oiio = _oiio()
    if oiio is None:
        f, parts = _raw_exr(path)
        part, index = _choose_depth(parts, channel, path)
        ptype = part.spec.types[index]
        if ptype == 0:
            raise ImageFileError(
                path, f"depth channel '{part.qualified(index)}' ({part.label}) holds "
                      f"{rawexr.PIXEL_TYPE_NAMES[ptype]} values; depth must be stored as floating-point metres "
                      f"(EXR or .npy)")
        _check_read(path, part, 1)
        data = _raw_read_channels(f, part, [index], path)
        data = _to_display_window(data, part.spec, np.nan)[..., 0]
        return np.ascontiguousarray(data, dtype=np.float32)
    inp = _open(path, oiio)
    try:
        parts = _parts(inp, path)
        part, index = _choose_depth(parts, channel, path)
        formats = part.spec.channelformats
        ctype = formats[index] if formats else part.spec.format
        if not _is_float(ctype):
            raise ImageFileError(
                path, f"depth channel '{part.qualified(index)}' ({part.label}) holds {ctype} values; "
                      f"depth must be stored as floating-point metres (EXR or .npy)")
        _check_read(path, part, 1)
        data = _read_channels(inp, part, [index], path)
    finally:
        inp.close()
    data = _to_display_window(data, part.spec, np.nan)[..., 0]
    return np.ascontiguousarray(data, dtype=np.float32)


def _png_jpeg_size(path: Path):
    """(height, width) from a PNG's IHDR or a JPEG's SOF marker; None if
    neither (or the header is cut short)."""
    import struct
    with open(path, "rb") as f:
        head = f.read(24)
        if head.startswith(b"\x89PNG\r\n\x1a\n"):
            if len(head) < 24 or head[12:16] != b"IHDR":
                return None
            w, h = struct.unpack(">II", head[16:24])
            return h, w
        if not head.startswith(b"\xff\xd8"):
            return None
        f.seek(2)
        while True:                                     # one marker segment at a time (a few dozen)
            mark = f.read(4)
            if len(mark) < 4 or mark[0] != 0xFF:
                return None
            kind, size = mark[1], struct.unpack(">H", mark[2:])[0]
            if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):
                seg = f.read(5)
                if len(seg) < 5:
                    return None
                h, w = struct.unpack(">HH", seg[1:5])
                return h, w
            if size < 2:                                # a segment's size counts its own 2 bytes
                return None
            f.seek(size - 2, 1)


def _oiio_header(path: Path, oiio):
    """(parts, format name) of a file, from its header through OpenImageIO."""
    inp = _open(path, oiio)
    try:
        return _parts(inp, path), inp.format_name()
    finally:
        inp.close()


def _colour_part(parts, fmt, path, strict: bool):
    """The part :func:`read_image` reads; where none holds colour, the first
    (its size is still the file's), unless ``strict``."""
    try:
        return _choose_colour(parts, fmt, path)[0]
    except ImageFileError:
        if strict:
            raise
        return parts[0]


def image_size(path, *, pixels: bool = False) -> tuple[int, int]:
    """(height, width) px of the image :func:`read_image` returns, from the
    file's header only: an EXR colour part's display window where the data
    is placed in it, else its data window (the size the memory guard must
    see: what is allocated); :class:`ImageFileError` naming the file when
    it cannot be read. ``pixels``: refuse also a file whose pixels
    :func:`read_image` could not decode here (without OpenImageIO: anything
    but a scanline EXR that rawexr reads)."""
    path = Path(path)
    oiio = _oiio()
    if oiio is not None:
        parts, fmt = _oiio_header(path, oiio)
        return _returned_size(_colour_part(parts, fmt, path, pixels).spec)
    _check_file(path)
    if _kind_of(path) != "exr" and not pixels:
        try:
            size = _png_jpeg_size(path)
        except OSError as e:
            raise ImageFileError(path, f"cannot be read ({e.strerror})") from None
        if size is None:
            raise ImageFileError(path, f"cannot be read as a PNG or JPEG image without OpenImageIO: "
                                       f"{NO_OPENIMAGEIO}")
        return size
    f, parts = _raw_exr(path, header_only=True)
    part = _colour_part(parts, "openexr", path, pixels)
    if pixels:
        raw = f.parts[part.index]
        if raw.kind != "scanlineimage":
            raise ImageFileError(path, f"{part.label} is a {raw.kind} part, which dcdi's own EXR reader does not "
                                       f"read: {NO_OPENIMAGEIO}, or write it as a scanline EXR")
        if raw.compression not in rawexr.READ_COMPRESSIONS:
            raise ImageFileError(path, f"{part.label} is compressed with {raw.compression_name}, "
                                       f"which dcdi's own EXR reader does not read: {NO_OPENIMAGEIO}, or write "
                                       "it uncompressed or ZIP-compressed")
    return _returned_size(part.spec)


def depth_size(path, *, channel=None) -> tuple[int, int]:
    """(height, width) px of the depth map :func:`read_depth` returns (or
    ``dataset.rgbd.read_any_depth``), from the header only: a .npy's shape,
    an EXR depth part's display or data window (the part and channel chosen
    as :func:`read_depth` chooses them), another format's first image."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        return _npy_header(path)[0]
    _check_file(path)
    if _kind_of(path) != "exr":
        return image_size(path)
    oiio = _oiio()
    parts = _raw_exr(path, header_only=True)[1] if oiio is None else _oiio_header(path, oiio)[0]
    part, _ = _choose_depth(parts, channel, path)
    return _returned_size(part.spec)


def check_job_inputs(job: str, image, depth=None, *, depth_channel=None) -> None:
    """Refuse, from the headers alone (before any pixel is read), a job's
    inputs that cannot be read together: the image too large for ``job``
    (``memory.check_image_job``; a job it does not know counts as the
    hungriest), the depth map too large to read, or a depth map whose size
    differs from the image's (the error names both files and sizes).
    ``depth``: the depth map's path, or None; ``depth_channel`` as
    :func:`read_depth`'s ``channel``."""
    if job not in memory.JOB_BYTES_PER_PIXEL:
        job = max(memory.JOB_BYTES_PER_PIXEL, key=memory.JOB_BYTES_PER_PIXEL.get)
    h, w = image_size(image)
    memory.check_image_job(h, w, job, f"the image {image}")
    if depth is None:
        return
    dh, dw = depth_size(depth, channel=depth_channel)
    if (dh, dw) != (h, w):              # the likelier mistake, said first
        raise ImageFileError(depth, f"the depth map is {dw} x {dh} px (width x height) but the image {image} is "
                                    f"{w} x {h} px; they must be the same size")
    memory.check_fits(dh * dw * _READ_BYTES_PER_SAMPLE, f"the depth map {depth}: {dw} x {dh} px",
                      "use a smaller depth map")


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------

def _as_rgb(image, path):
    a = np.asarray(image)
    if a.dtype.kind != "f":
        raise ImageFileError(
            path, f"the image to write must be floating-point linear light; got dtype {a.dtype} "
                  f"(for 8-bit sRGB data use srgb_to_linear(x / 255))")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ImageFileError(path, f"the image to write must have shape (H, W) or (H, W, 3); got {np.shape(image)}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageFileError(path, f"the image to write is empty (shape {np.shape(image)})")
    a = np.ascontiguousarray(a, dtype=np.float32)
    _check_finite(a, path, "the image")
    return a


def _check_finite(a, path, what):
    bad = ~np.isfinite(a)
    if bad.any():
        where = np.argwhere(bad)[0]
        at = f"row {where[0]}, column {where[1]}"
        if a.ndim == 3:
            at += f", channel {'RGB'[where[2]]}"
        raise ImageFileError(
            path, f"refusing to write {what} with {int(bad.sum())} non-finite value(s) (NaN or inf "
                  f"as float32); the first is {a[tuple(where)]} at {at}")


def _write(path: Path, fmt, pixels, typename, channelnames, attributes):
    """Write (h, w, c) ``pixels`` atomically with OpenImageIO's ``fmt`` writer
    (without OpenImageIO, EXR with rawexr: ZIP, as OpenImageIO writes it)."""
    oiio = _oiio()
    pixels = np.ascontiguousarray(pixels)
    # OpenImageIO's Python write_image misreads a 2-D array for a one-channel
    # image (it wants (h, w, c)); callers always pass three dimensions.
    assert pixels.ndim == 3
    h, w, c = pixels.shape
    if oiio is None:
        _check_writable(path, fmt)
        strings = {k: v for k, v in attributes.items() if k != "compression"}
        data = rawexr.encode_exr({n: pixels[..., i] for i, n in enumerate(channelnames)}, pixel_type=typename,
                                 compression=attributes.get("compression", "zip").upper(), strings=strings,
                                 path=path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                f.write(data)
        return
    with atomic_path(path) as tmp:
        # The writer is chosen by format name, not by the temporary's suffix
        # (which ends in the real extension anyway: '.name.XXXX.tmp.png').
        out = oiio.ImageOutput.create(fmt)
        if out is None:
            raise ImageFileError(path, f"OpenImageIO cannot write {fmt} files ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, oiio.TypeDesc(typename))
        spec.channelnames = tuple(channelnames)
        # no DateTime stamp: the same pixels must give the same bytes (datasets are compared by hash)
        spec.attribute("DateTime", "")
        for key, value in attributes.items():
            spec.attribute(key, value)
        # OpenImageIO 3.1 (Debian's build: debug on) prints a line for the empty DateTime on every write
        debug = oiio.get_int_attribute("debug", 0)
        oiio.attribute("debug", 0)
        try:
            if not out.open(str(tmp), spec):
                raise ImageFileError(path, f"cannot be written ({out.geterror()})")
            ok = out.write_image(pixels)
            err = out.geterror() if not ok else ""
            closed = out.close()
        finally:
            oiio.attribute("debug", debug)
        if not ok or not closed:
            raise ImageFileError(path, f"cannot be written ({err or out.geterror() or 'write failed'})")


def _check_writable(path: Path, fmt: str) -> None:
    if fmt != "openexr" and _oiio() is None:
        raise ImageFileError(path, f"cannot write {fmt.upper()} files without OpenImageIO: {NO_OPENIMAGEIO}, "
                                   "or write .exr")


def check_image_output(path) -> Path:
    """Refuse, before any work, an output path whose extension cannot be
    written (the same rule as :func:`write_image`; without OpenImageIO only
    .exr is written)."""
    path = Path(path)
    if path.suffix.lower() not in _WRITE_FORMATS:
        raise ImageFileError(path, f"cannot write images with extension '{path.suffix}'; allowed: "
                                   f"{', '.join(_WRITE_FORMATS)}")
    _check_writable(path, _WRITE_FORMATS[path.suffix.lower()][0])
    return path


def write_image(path, image, *, bit_depth=None, record=None) -> None:
    """Write a linear-light image, the format chosen by the extension.

    ``.exr``: linear RGB, float32 (half with ``bit_depth=16``); ``.png``:
    sRGB-encoded, clipped to [0, 1], 8-bit (16 with ``bit_depth=16``);
    ``.jpg``/``.jpeg``: 8-bit sRGB. ``image`` is ``(H, W)`` (grey, written as
    three equal channels) or ``(H, W, 3)``, floating point. A NaN or inf
    anywhere raises :class:`ImageFileError` and writes nothing. Missing folders
    are created; the file appears only once completely written.

    ``record``: how the image was made (``capture_record.CaptureRecord``),
    kept in the EXR header, else in the sidecar ``<path>.dcdi.json`` written
    after the image; None removes a sidecar left by an earlier write.
    """
    from .capture_record import CaptureRecord, EXR_ATTRIBUTE, has_header, write_sidecar
    if record is not None and not isinstance(record, CaptureRecord):
        raise ImageFileError(path, f"record {record!r}: a CaptureRecord, or None")
    path = check_image_output(path)
    ext = path.suffix.lower()
    fmt, allowed, default = _WRITE_FORMATS[ext]
    bits = default if bit_depth is None else bit_depth
    if bits not in allowed:
        raise ImageFileError(
            path, f"bit_depth={bit_depth!r} is not supported for {ext} files; allowed: "
                  f"{', '.join(map(str, allowed))}")
    rgb = _as_rgb(image, path)
    if fmt == "openexr":
        if bits == 16:
            big = np.abs(rgb) > _HALF_MAX
            if big.any():
                raise ImageFileError(
                    path, f"{int(big.sum())} value(s) exceed the half-float range "
                          f"(|x| <= {_HALF_MAX:g}; largest {float(np.abs(rgb).max()):g}); "
                          f"write float32 (bit_depth=None) instead")
        attributes = {"compression": "zip"}
        if record is not None:
            attributes[EXR_ATTRIBUTE] = record.as_json()
        _write(path, fmt, rgb, "half" if bits == 16 else "float", "RGB", attributes)
        return
    top = 65535 if bits == 16 else 255
    encoded = linear_to_srgb(np.clip(rgb.astype(np.float64), 0.0, 1.0))
    pixels = np.rint(encoded * top).astype(np.uint16 if bits == 16 else np.uint8)
    attributes = {"oiio:ColorSpace": "sRGB"}
    if fmt == "jpeg":
        attributes["Compression"] = "jpeg:95"
    _write(path, fmt, pixels, "uint16" if bits == 16 else "uint8", "RGB", attributes)
    if not has_header(path):
        write_sidecar(path, record)


DEPTH_SUFFIXES = (".exr", ".npy")


def check_depth_output(path) -> Path:
    """Refuse, before any work, a depth map's output path that
    :func:`write_depth` cannot write (.exr or .npy)."""
    path = Path(path)
    if path.suffix.lower() not in DEPTH_SUFFIXES:
        raise ImageFileError(path, f"depth maps are written as .exr (or .npy); got extension '{path.suffix}'")
    return path


def write_depth(path, depth) -> None:
    """Write a float32 ``(H, W)`` depth map (metres) as a one-channel 'Z' EXR.

    Values are stored as given: inf (infinity) and NaN (invalid pixel) are
    kept. A ``.npy`` path writes a NumPy array instead. Atomic, like
    :func:`write_image`.
    """
    path = Path(path)
    d = _as_depth(depth, path)
    ext = path.suffix.lower()
    if ext == ".npy":
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, d, allow_pickle=False)
        return
    check_depth_output(path)
    _write(path, "openexr", d[..., None], "float", ("Z",), {"compression": "zip"})

