"""The checks made before a pixel is read or written: the size of what a
reader returns, from the header alone (``image_size``, ``depth_size``: an
EXR's display window where the data is placed in it), and a display window
far larger than its data window refused (``_check_read``, with the memory
guard); a job's inputs that cannot be read together
(``check_job_inputs``: too large for the memory, or an image and a depth
map of different sizes); an output path that cannot be written
(``check_image_output``, ``check_depth_output``)."""
from __future__ import annotations

from pathlib import Path

from .. import memory
from . import rawexr
from .image_file import (NO_OPENIMAGEIO, ImageFileError, _check_file, _choose_depth, _colour_part, _kind_of,
                         _npy_header, _oiio, _oiio_header, _raw_exr, _RawSpec)

__all__ = ["DISPLAY_PAD_MAX_PX", "DISPLAY_PAD_FACTOR", "DEPTH_SUFFIXES", "image_size", "depth_size",
           "check_job_inputs", "check_image_output", "check_depth_output"]

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

# extension -> (OpenImageIO format name, allowed bit depths, default bit depth)
_WRITE_FORMATS = {
    ".exr": ("openexr", (32, 16), 32),
    ".png": ("png", (8, 16), 8),
    ".jpg": ("jpeg", (8,), 8),
    ".jpeg": ("jpeg", (8,), 8),
}

DEPTH_SUFFIXES = (".exr", ".npy")


def _displayed(spec) -> bool:
    """Whether the readers return the display window (EXR may differ from
    the data window) rather than the data window itself."""
    same = (spec.x, spec.y, spec.width, spec.height) == (spec.full_x, spec.full_y, spec.full_width, spec.full_height)
    return not same and spec.full_width > 0 and spec.full_height > 0


def _returned_size(spec) -> tuple[int, int]:
    """(height, width) px of what the readers return for a part: the
    display window where the readers place the data in it
    (``images._to_display_window``), else the data window."""
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


def image_size(path, *, pixels: bool = False) -> tuple[int, int]:
    """(height, width) px of the image :func:`~dcdi_core.io.images.read_image` returns, from the
    file's header only: an EXR colour part's display window where the data
    is placed in it, else its data window (the size the memory guard must
    see: what is allocated); :class:`~dcdi_core.io.image_file.ImageFileError` naming the file when
    it cannot be read. ``pixels``: refuse also a file whose pixels
    :func:`~dcdi_core.io.images.read_image` could not decode here (without OpenImageIO: anything
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
    """(height, width) px of the depth map :func:`~dcdi_core.io.images.read_depth` returns (or
    ``dataset.rgbd.read_any_depth``), from the header only: a .npy's shape,
    an EXR depth part's display or data window (the part and channel chosen
    as :func:`~dcdi_core.io.images.read_depth` chooses them), another format's first image."""
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
    :func:`~dcdi_core.io.images.read_depth`'s ``channel``."""
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


def _check_writable(path: Path, fmt: str) -> None:
    if fmt != "openexr" and _oiio() is None:
        raise ImageFileError(path, f"cannot write {fmt.upper()} files without OpenImageIO: {NO_OPENIMAGEIO}, "
                                   "or write .exr")


def check_image_output(path) -> Path:
    """Refuse, before any work, an output path whose extension cannot be
    written (the same rule as :func:`~dcdi_core.io.images.write_image`; without OpenImageIO only
    .exr is written)."""
    path = Path(path)
    if path.suffix.lower() not in _WRITE_FORMATS:
        raise ImageFileError(path, f"cannot write images with extension '{path.suffix}'; allowed: "
                                   f"{', '.join(_WRITE_FORMATS)}")
    _check_writable(path, _WRITE_FORMATS[path.suffix.lower()][0])
    return path


def check_depth_output(path) -> Path:
    """Refuse, before any work, a depth map's output path that
    :func:`~dcdi_core.io.images.write_depth` cannot write (.exr or .npy)."""
    path = Path(path)
    if path.suffix.lower() not in DEPTH_SUFFIXES:
        raise ImageFileError(path, f"depth maps are written as .exr (or .npy); got extension '{path.suffix}'")
    return path
