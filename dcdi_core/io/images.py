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
  :class:`~dcdi_core.io.image_file.ImageFileError`.

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
:class:`~dcdi_core.io.image_file.ImageFileError` in one line naming the
file and what to install.

What a file holds (its parts, and which channels are the colour and the
depth) is read by :mod:`dcdi_core.io.image_file`; the bounds checked before
a pixel is read or written, and the checks of a job's inputs and outputs,
are :mod:`dcdi_core.io.image_checks`.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import rawexr
from .. import memory
from ..atomic import atomic_path
from .image_checks import (_WRITE_FORMATS, _check_read, _check_writable, _displayed, check_depth_output,
                           check_image_output)
from .image_file import (_LINEAR_FORMATS, ImageFileError, _choose_colour, _choose_depth, _is_float, _npy_header,
                         _oiio, _open, _parts, _raw_exr, _raw_read_channels, _read_channels)

__all__ = [
    "read_image",
    "write_image",
    "read_depth",
    "write_depth",
    "srgb_to_linear",
    "linear_to_srgb",
]

_HALF_MAX = 65504.0


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
    ``'<part>.<channel>'``), else the first of :data:`~dcdi_core.io.image_file.DEPTH_CHANNELS` found,
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
            if os.path.getsize(tmp) != len(data):          # a full disk that did not say so
                raise ImageFileError(path, f"the written file holds {os.path.getsize(tmp)} of its {len(data)} "
                                           "bytes (is the disk full?)")
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
        _read_back(oiio, tmp, path, (h, w, c))


def _read_back(oiio, tmp, path, shape) -> None:
    """The temporary just written, read whole before it is renamed into
    place: a writer that reported success on a full disk (a truncated PNG)
    is an error here, never a file that cannot be opened."""
    inp = oiio.ImageInput.open(str(tmp))
    if inp is None:
        raise ImageFileError(path, f"the written file cannot be read back (is the disk full?): {oiio.geterror()}")
    try:
        spec = inp.spec()
        got = (spec.height, spec.width, spec.nchannels)
        data = inp.read_image() if got == tuple(shape) else None
        why = inp.geterror()
    finally:
        inp.close()
    if got != tuple(shape) or data is None or why:
        raise ImageFileError(path, f"the written file cannot be read back (is the disk full?): "
                                   f"{why or f'it holds {got[0]} x {got[1]} x {got[2]}, not {shape}'}")



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

