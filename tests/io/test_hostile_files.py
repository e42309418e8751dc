"""Hostile image and record files: every public reader reads them, or
refuses them with one project error (DcdiError, one line), within a memory
bound, and never lets another exception out.

Valid files (rawexr's NONE, ZIPS and ZIP EXRs, one and four channels, float
and half, each with a capture record; a PNG and a JPEG; record sidecars)
are mutated structurally: header fields (windows, attribute sizes,
chunkCount, the compression byte, channel types, the part type, the version
flags), the offset table, the chunks' fields, truncation, zlib bombs, JSON
records nested or huge. They are read by read_image, read_depth,
image_size, depth_size, check_job_inputs, rawexr.ExrFile(...).read and
capture_record.read_record, with OpenImageIO and without.

The memory bound: the peak of Python's allocations (tracemalloc, which sees
numpy's arrays; OpenImageIO's own buffers it does not) stays below
PEAK_BYTES while the memory guard is told the machine has GUARD_BYTES free.
A reader may allocate beyond what a file of a few KB can hold only with the
guard's leave (a display window may pad 4 x 4 pixels to an 8192 x 8192
frame on a machine that has the memory for it), so the guard's figure is
what bounds the rest.

Profiles as in tests/test_properties.py (tests/conftest.py): a few
derandomised examples by default, 300 random ones under
DCDI_HYPOTHESIS_PROFILE=long. Each property also runs against a planted bug
that it must catch. Below them, one deterministic test (or a few) per
finding of the hostile-input review, numbered as the review numbers them;
each fails on the readers before the fix.
"""
from __future__ import annotations

import functools
import json
import os
import struct
import sys
import tracemalloc
import warnings
import zlib
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dcdi_core import memory
from dcdi_core.errors import DcdiError, MemoryLimitError
from dcdi_core.io import capture_record as cr
from dcdi_core.io import image_checks, images, rawexr
from dcdi_core.io.image_file import ImageFileError, have_openimageio

PEAK_BYTES = 64 << 20
GUARD_BYTES = 48 << 20
FIXTURES = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large]
HAVE_OIIO = have_openimageio()
H, W = 20, 9
RECORD = cr.CaptureRecord(kind="simulated", lens_id="mos-s1", pixel_pitch_mm=0.0122, axis_px=(10.0, 4.5),
                          image_size=(H, W), focus_distance_m=1.5, software="dcdi test")


# ------------------------------------------------------------------ the bound and the rule
@contextmanager
def guarded(oiio: bool = True):
    """The memory guard sees a machine with GUARD_BYTES free; without
    OpenImageIO when ``oiio`` is False (as a distribution's Blender)."""
    with pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "available_bytes", lambda: GUARD_BYTES)
        if not oiio:
            m.setitem(sys.modules, "OpenImageIO", None)
        yield


def bounded(call):
    """call()'s result, or None where it refused with a one-line DcdiError;
    any other exception goes through. Its peak Python allocation must stay
    below PEAK_BYTES."""
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return call()
    except DcdiError as e:
        assert "\n" not in str(e), repr(str(e))
        return None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < PEAK_BYTES, f"peak Python allocation {peak} bytes (bound {PEAK_BYTES})"


def refused(call, error=DcdiError) -> str:
    """The one-line message of the ``error`` that call() raises, within the bound."""
    got = []

    def keep():
        try:
            call()
        except error as e:
            got.append(str(e))
            raise
    bounded(keep)
    assert got, "not refused"
    return got[0]


def read_everything(path: Path) -> None:
    """Every public reader on ``path``, each bounded (with and without OpenImageIO)."""
    for oiio in ((True, False) if HAVE_OIIO else (False,)):
        with guarded(oiio):
            for call in (lambda: images.read_image(path), lambda: images.read_depth(path),
                         lambda: image_checks.image_size(path), lambda: image_checks.image_size(path, pixels=True),
                         lambda: image_checks.depth_size(path), lambda: cr.read_record(path),
                         lambda: image_checks.check_job_inputs("correct", path, path)):
                bounded(call)
    with guarded(False):
        bounded(lambda: [f.read(p.index) for f in [rawexr.ExrFile(path)] for p in f.parts])
        bounded(lambda: rawexr.ExrFile(path, header_only=True))


# ------------------------------------------------------------------ valid files, and the EXR's layout
def valid_exr(compression: str, names: tuple, ptype: str, *, strings=None, shape=(H, W)) -> bytes:
    """A one-part EXR of rawexr's with a capture record: smooth rows on top
    (zlib shrinks them), noise below (stored raw)."""
    h, w = shape
    rng = np.random.default_rng(len(names))
    chans = {}
    for n in names:
        a = rng.random((h, w), dtype=np.float32) * 4 + 0.1
        a[:h // 2] = 1.5
        chans[n] = a
    strings = {cr.EXR_ATTRIBUTE: RECORD.as_json()} if strings is None else strings
    return rawexr.encode_exr(chans, pixel_type=ptype, compression=compression, strings=strings)


EXRS = [valid_exr(c, names, p) for c in ("NONE", "ZIPS", "ZIP") for names, p in ((("Z",), "float"),
                                                                                    (("B", "G", "R", "Z"), "half"))]


def attributes(data: bytes) -> tuple[list, int]:
    """[(name, type, value position, size)] of a one-part EXR's header, and where its offset table starts."""
    out, pos = [], 8
    while data[pos] != 0:
        name_end = data.index(b"\0", pos)
        type_end = data.index(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        out.append((data[pos:name_end].decode(), data[name_end + 1:type_end].decode(), type_end + 5, size))
        pos = type_end + 5 + size
    return out, pos + 1


def value_at(data: bytes, name: str) -> int:
    """Where attribute ``name``'s value starts."""
    return next(v for n, _, v, _ in attributes(data)[0] if n == name)


def table(data: bytes) -> tuple[int, list]:
    """(where the offset table starts, its entries) of a valid one-part EXR."""
    return attributes(data)[1], [int(o) for o in rawexr.ExrFile("valid", data)._tables[0]]


def with_header(data: bytes, changes: dict) -> bytes:
    """``data`` with header attributes replaced or added ({name: (type, value
    bytes)}) or removed ({name: None}), the offset table following the header."""
    attrs, end = attributes(data)
    items = {n: (t, data[v:v + s]) for n, t, v, s in attrs}
    for n, tv in changes.items():
        if tv is None:
            items.pop(n, None)
        else:
            items[n] = tv
    header = b"".join(rawexr._attr(n, t, v) for n, (t, v) in sorted(items.items())) + b"\0"
    at, offsets = table(data)
    shift = 8 + len(header) - at
    moved = struct.pack(f"<{len(offsets)}Q", *[(o + shift) % 2 ** 64 for o in offsets])
    return data[:8] + header + moved + data[at + 8 * len(offsets):]


def patched(data: bytes, at: int, fmt: str, *values) -> bytes:
    b = bytearray(data)
    struct.pack_into(fmt, b, at, *values)
    return bytes(b)


@functools.lru_cache(maxsize=None)
def zlib_bomb(inflated: int = 128 << 20) -> bytes:
    """A valid-looking ZIP EXR (16 x 4 px, one chunk of 256 raw bytes) whose
    chunk is a zlib stream of ``inflated`` zero bytes (about inflated / 1000
    bytes of file)."""
    data = rawexr.encode_exr({"Z": np.zeros((16, 4), np.float32)}, compression="ZIP")
    off = table(data)[1][0]
    z = zlib.compressobj(9)
    zero = bytes(1 << 20)
    stream = b"".join([z.compress(zero) for _ in range(inflated >> 20)] + [z.flush()])
    return data[:off] + struct.pack("<ii", 0, len(stream)) + stream


def crc_fixed_png(data: bytes) -> bytes:
    """A PNG's IHDR with its CRC recomputed (so that a changed size is believed)."""
    return patched(data, 29, ">I", zlib.crc32(data[12:29]))


@functools.lru_cache(maxsize=None)
def valid_image(suffix: str, tmp: str) -> bytes:
    path = Path(tmp) / f"valid{suffix}"
    images.write_image(path, np.random.default_rng(1).random((H, W, 3), dtype=np.float32))
    return path.read_bytes()


# ------------------------------------------------------------------ mutations
INTERESTING = st.one_of(st.integers(-4, 70), st.sampled_from(
    [-2 ** 31, -2 ** 31 + 1, -1, 2 ** 31 - 1, 2 ** 30, 1 << 24, 65535, 20000, 19999, -20000, 10 ** 6, 33_333_332]))


def m_window(draw, data):
    """A data or display window's coordinates."""
    at = value_at(data, draw(st.sampled_from(["dataWindow", "displayWindow"])))
    return patched(data, at, "<iiii", *[draw(INTERESTING) for _ in range(4)])


def m_attribute_size(draw, data):
    """An attribute's size field (the parser must not believe it)."""
    attrs = attributes(data)[0]
    name, _, at, size = attrs[draw(st.integers(0, len(attrs) - 1))]
    new = draw(st.one_of(INTERESTING, st.sampled_from([size - 1, size + 1, 0, size * 1000])))
    return patched(data, at - 4, "<i", max(-2 ** 31, min(2 ** 31 - 1, new)))


def m_header_value(draw, data):
    """A standard attribute replaced by one of another type, size or value, or removed."""
    name = draw(st.sampled_from(["chunkCount", "compression", "type", "dataWindow", "displayWindow", "name",
                                 "channels", "tiles"]))
    typ = {"chunkCount": "int", "compression": "compression", "type": "string", "name": "string",
           "channels": "chlist", "tiles": "tiledesc"}.get(name, "box2i")
    typ = draw(st.sampled_from([typ, typ, "int", "string", "box2f"]))
    value = draw(st.one_of(
        st.binary(max_size=20),
        INTERESTING.map(lambda v: struct.pack("<i", v)),
        st.integers(0, 255).map(lambda v: bytes([v])),
        st.sampled_from([b"scanlineimage", b"tiledimage", b"deepscanline", b"deeptile"]),
        st.lists(INTERESTING, min_size=4, max_size=4).map(lambda v: struct.pack("<iiii", *v)),
        channel_list()))
    return with_header(data, {name: draw(st.sampled_from([(typ, value), None]))})


def channel_list():
    """A chlist: names with pixel types and sampling drawn (the valid ones included)."""
    one = st.tuples(st.sampled_from(["R", "G", "B", "Z", "A", "Y", "x" * 40]),
                    st.one_of(st.integers(0, 2), INTERESTING),
                    st.sampled_from([(1, 1), (1, 1), (2, 2), (0, 1), (-1, 3)]))
    return st.lists(one, max_size=5).map(lambda cs: b"".join(
        n.encode() + b"\0" + struct.pack("<iB3xii", t, 0, *s) for n, t, s in cs) + b"\0")


def m_channel_type(draw, data):
    """The first channel's pixel type in place."""
    at = value_at(data, "channels")
    at = data.index(b"\0", at) + 1
    return patched(data, at, "<i", draw(st.one_of(st.integers(-1, 4), INTERESTING)))


def m_compression(draw, data):
    return patched(data, value_at(data, "compression"), "<B", draw(st.integers(0, 255)))


def m_flags(draw, data):
    """The version word: tiled, long names, deep, multi-part flags, another version."""
    flags = draw(st.sampled_from([2, 1, 3, 0xFF])) | draw(st.sampled_from([0, 0x200, 0x400, 0x800, 0x1000, 0x1200,
                                                                          0x1800, 0x1E00]))
    return patched(data, 4, "<I", flags)


def m_offset(draw, data):
    """An offset table entry: outside the file, at another chunk, just off."""
    at, offsets = table(data)
    i = draw(st.integers(0, len(offsets) - 1))
    new = draw(st.one_of(st.sampled_from([0, len(data) - 1, len(data), len(data) + 8, 2 ** 63, 2 ** 64 - 1,
                                          offsets[0], offsets[-1], at]),
                         st.integers(-16, 16).map(lambda d: max(0, offsets[i] + d))))
    return patched(data, at + 8 * i, "<Q", new)


def m_chunk(draw, data):
    """A chunk's first scanline or byte count."""
    _, offsets = table(data)
    off = draw(st.sampled_from(offsets)) + draw(st.sampled_from([0, 4]))
    (old,) = struct.unpack_from("<i", data, off)
    new = draw(st.one_of(INTERESTING, st.integers(-8, 8).map(lambda d: old + d)))
    return patched(data, off, "<i", max(-2 ** 31, min(2 ** 31 - 1, new)))


def m_truncate(draw, data):
    return data[:draw(st.integers(0, len(data) - 1))]


def m_flip(draw, data):
    b = bytearray(data)
    for _ in range(draw(st.integers(1, 8))):
        b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
    return bytes(b)


def m_bomb(draw, data):
    """A chunk that inflates to 128 MiB, whole or cut short."""
    bomb = zlib_bomb()
    return bomb[:draw(st.sampled_from([len(bomb), len(bomb) - 1, len(bomb) // 2]))]


EXR_MUTATIONS = [m_window, m_attribute_size, m_header_value, m_channel_type, m_compression, m_flags, m_offset,
                 m_chunk, m_truncate, m_flip, m_bomb]


@st.composite
def hostile_exr(draw) -> bytes:
    data = draw(st.sampled_from(EXRS))
    for k, how in enumerate(draw(st.lists(st.sampled_from(EXR_MUTATIONS), min_size=1, max_size=2))):
        if k and not still_valid(data):
            break                                       # the next mutation needs a valid layout
        data = how(draw, data)
    return data


def still_valid(data: bytes) -> bool:
    """Whether rawexr reads ``data`` (then its layout is a valid one-part EXR's)."""
    try:
        attributes(data)
        rawexr.ExrFile("mutated", data).read()
    except Exception:
        return False
    return True


JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70) | st.floats()
                           | st.text(max_size=12),
                           lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=6), kids,
                                                                                     max_size=3), max_leaves=12)
FIELDS = [f for f in json.loads(RECORD.as_json())] + ["noise.full_well_electrons", "colour"]


@st.composite
def hostile_record(draw) -> bytes:
    """A record's bytes: a field changed, nested deep, grown huge, or not text."""
    how = draw(st.sampled_from(["field", "field", "nested", "huge", "bytes", "json"]))
    d = json.loads(RECORD.as_json())
    if how == "field":
        name = draw(st.sampled_from(FIELDS))
        value = draw(JSON_VALUES)
        if name.startswith("noise."):
            d["noise"] = {"full_well_electrons": value, "read_noise_electrons": 1.0, "seed": 1}
        elif draw(st.booleans()) and name != "format":
            d.pop(name, None)
        else:
            d[name] = value
        return json.dumps(d).encode()
    if how == "nested":
        n = draw(st.sampled_from([cr.RECORD_MAX_DEPTH - 1, cr.RECORD_MAX_DEPTH, cr.RECORD_MAX_DEPTH + 1, 1000,
                                  30_000, 100_000]))
        inner = draw(st.sampled_from(["[" * n + "]" * n, '{"a":' * n + "1" + "}" * n, "[" * n, '"[[[' * 3]))
        d["extra"] = "@"
        return json.dumps(d).replace('"@"', inner).encode()
    if how == "huge":
        size = draw(st.sampled_from([cr.RECORD_MAX_BYTES - 200, cr.RECORD_MAX_BYTES + 1, 1 << 20]))
        d["extra"] = {"pad": "x" * size}
        return json.dumps(d).encode()
    if how == "json":
        return json.dumps(draw(JSON_VALUES)).encode()
    return draw(st.binary(max_size=64))


# ------------------------------------------------------------------ the properties
@pytest.mark.property
@given(data=hostile_exr())
@settings(suppress_health_check=FIXTURES)
def test_a_hostile_exr_is_read_or_refused_with_one_project_error_within_bounds(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("exr") / "f.exr"
    path.write_bytes(data)
    read_everything(path)


@pytest.mark.property
@given(text=hostile_record(), where=st.sampled_from(["sidecar", "exr"]))
@settings(suppress_health_check=FIXTURES)
def test_a_hostile_record_is_read_or_refused_with_one_capture_record_error(tmp_path_factory, text, where):
    folder = tmp_path_factory.mktemp("record")
    if where == "sidecar":
        path = folder / "a.png"
        cr.sidecar_path(path).write_bytes(text)
    else:
        try:
            string = text.decode("utf-8")
        except UnicodeDecodeError:
            string = text.decode("latin-1")
        path = folder / "a.exr"
        path.write_bytes(valid_exr("ZIP", ("Z",), "float", strings={cr.EXR_ATTRIBUTE: string}))
    record = None
    try:
        record = bounded(lambda: cr.read_record(path))
    except DcdiError:
        pass
    if record is None:
        with pytest.raises(cr.CaptureRecordError) as e:
            cr.read_record(path)
        assert path.name in str(e.value)
    else:
        assert isinstance(record, cr.CaptureRecord)


@pytest.mark.property
@pytest.mark.skipif(not HAVE_OIIO, reason="PNG and JPEG are written with OpenImageIO")
@given(data=st.data(), suffix=st.sampled_from([".png", ".jpg"]))
@settings(suppress_health_check=FIXTURES)
def test_a_hostile_png_or_jpeg_is_read_or_refused_with_one_project_error_within_bounds(tmp_path_factory, data,
                                                                                     suffix):
    good = valid_image(suffix, str(tmp_path_factory.getbasetemp()))
    how = data.draw(st.sampled_from(["size", "size", "cut", "flip", "segment"]))
    if how == "size" and suffix == ".png":
        bad = patched(good, 16, ">II", *[data.draw(st.sampled_from([0, 1, 20000, 65535, 2 ** 31 - 1, 2 ** 32 - 1]))
                                         for _ in range(2)])
        bad = crc_fixed_png(bad) if data.draw(st.booleans()) else bad
    elif how in ("size", "segment"):
        b, at = bytearray(good), data.draw(st.integers(2, 200))
        at = good.index(b"\xff", at) if b"\xff" in good[at:] else 2
        b[at + 2:at + 4] = data.draw(st.sampled_from([b"\0\0", b"\0\1", b"\xff\xff", b"\0\2"]))
        bad = bytes(b)
    elif how == "cut":
        bad = good[:data.draw(st.integers(0, len(good) - 1))]
    else:
        b = bytearray(good)
        for _ in range(data.draw(st.integers(1, 8))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
        bad = bytes(b)
    path = tmp_path_factory.mktemp("img") / f"f{suffix}"
    path.write_bytes(bad)
    read_everything(path)


def test_the_exr_property_finds_a_planted_bug(tmp_path, monkeypatch):
    """Readers as they were (an unbounded inflate, a chunkCount unpacked
    unchecked) break the property: it can fail."""
    path = tmp_path / "bomb.exr"
    path.write_bytes(zlib_bomb())
    read_everything(path)

    def unbounded(data, expect, path, where):                      # planted: zlib.decompress without a bound
        flat = zlib.decompress(data)
        raise rawexr.RawExrError(path, f"{where} decompresses to {len(flat)} bytes, expected {expect}")
    with monkeypatch.context() as m:
        m.setattr(rawexr, "_zip_decode", unbounded)
        with pytest.raises(AssertionError, match="peak Python allocation"):
            read_everything(path)
    path.write_bytes(with_header(EXRS[0], {"chunkCount": ("int", b"\1\0")}))
    read_everything(path)
    monkeypatch.setattr(rawexr, "_chunk_count", lambda h, path, label: struct.unpack("<i", h["chunkCount"][1])[0])
    with pytest.raises(struct.error):                               # planted: the unchecked unpack of before
        read_everything(path)


def test_the_record_property_finds_a_planted_bug(tmp_path, monkeypatch):
    side = cr.sidecar_path(tmp_path / "a.png")
    side.write_text('{"format": 1, "kind": "simulated", "extra": {"x": ' + "[" * 30_000 + "]" * 30_000 + "}}")
    refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    monkeypatch.setattr(cr, "_check_bounds", lambda text, path: None)    # planted: no depth bound
    with pytest.raises(RecursionError):
        cr.read_record(tmp_path / "a.png")


# ------------------------------------------------------------------ 1. zlib bombs, data windows the chunks cannot hold
def test_1_a_zlib_bomb_inflates_no_further_than_its_scanlines(tmp_path, capfd):
    path = tmp_path / "bomb.exr"
    path.write_bytes(zlib_bomb())
    assert path.stat().st_size < 200_000                        # 128 MiB of zeros in ~130 KB
    msg = refused(lambda: rawexr.ExrFile(path).read(), rawexr.RawExrError)
    assert str(path) in msg and "inflates to more than the 256 bytes its scanlines hold" in msg
    with guarded(oiio=False):
        msg = refused(lambda: images.read_depth(path), ImageFileError)
    assert "inflates to more than" in msg
    if HAVE_OIIO:                   # OpenEXR's own line about it is folded into the one error, not printed
        msg = refused(lambda: images.read_depth(path), ImageFileError)
        assert "packed data size says" in msg and capfd.readouterr().err == ""


@pytest.mark.parametrize("compression", ["NONE", "ZIP"])
def test_1_a_data_window_its_chunks_cannot_hold_is_refused_before_allocating(tmp_path, compression):
    """One scanline declared 33 million pixels wide (400 MB raw) in a file of a few hundred bytes."""
    data = valid_exr(compression, ("B", "G", "R"), "float", shape=(1, 4), strings={})
    path = tmp_path / "wide.exr"
    path.write_bytes(patched(data, value_at(data, "dataWindow"), "<iiii", 0, 0, 33_333_332, 0))
    msg = refused(lambda: rawexr.ExrFile(path).read(), rawexr.RawExrError)
    assert str(path) in msg and "33333333 x 1 px" in msg and "the header is damaged" in msg
    with guarded(oiio=False):
        refused(lambda: images.read_image(path))


# ------------------------------------------------------------------ 2. display windows
def display_padded(tmp_path, display=(0, 0, 19999, 19999)) -> Path:
    """4 x 4 pixels (RGB and Z) inside a display window of another size: a file of about 300 bytes."""
    data = valid_exr("ZIP", ("B", "G", "R", "Z"), "float", shape=(4, 4), strings={})
    path = tmp_path / "padded.exr"
    path.write_bytes(patched(data, value_at(data, "displayWindow"), "<iiii", *display))
    return path


@pytest.mark.parametrize("oiio", [True, False])
def test_2_image_size_is_the_display_window_the_readers_return(tmp_path, oiio):
    if oiio and not HAVE_OIIO:
        pytest.skip("OpenImageIO not installed")
    path = display_padded(tmp_path, (0, 0, 9, 5))
    with guarded(oiio):
        assert image_checks.image_size(path) == image_checks.depth_size(path) == (6, 10)
        assert images.read_image(path).shape == (6, 10, 3) and images.read_depth(path).shape == (6, 10)


@pytest.mark.parametrize("oiio", [True, False])
def test_2_a_display_window_absurdly_larger_than_its_data_is_refused_before_allocating(tmp_path, oiio):
    if oiio and not HAVE_OIIO:
        pytest.skip("OpenImageIO not installed")
    path = display_padded(tmp_path)
    with guarded(oiio), pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "available_bytes", lambda: 1 << 50)     # however much memory the machine has
        for read in (images.read_image, images.read_depth):
            msg = refused(lambda: read(path), ImageFileError)
            assert str(path) in msg and "display window 20000 x 20000 px around a data window of 4 x 4" in msg


@pytest.mark.parametrize("oiio", [True, False])
def test_2_padding_the_memory_guard_refuses_is_refused_before_allocating(tmp_path, oiio):
    """3000 x 3000 px around 4 x 4 (108 MB of RGB) on a machine with 48 MiB free."""
    if oiio and not HAVE_OIIO:
        pytest.skip("OpenImageIO not installed")
    path = display_padded(tmp_path, (0, 0, 2999, 2999))
    with guarded(oiio):
        assert image_checks.image_size(path) == (3000, 3000)
        for read in (images.read_image, images.read_depth):
            msg = refused(lambda: read(path), MemoryLimitError)
            assert str(path) in msg and "returned as 3000 x 3000 px" in msg


# ------------------------------------------------------------------ 3. every input of a job, from headers
def no_pixels(monkeypatch):
    """read_image and read_depth, made to fail: nothing may read pixels."""
    def read(*a, **k):
        raise AssertionError("pixels read")
    monkeypatch.setattr(images, "read_image", read)
    monkeypatch.setattr(images, "read_depth", read)
    monkeypatch.setattr(rawexr.ExrFile, "read", read)


@pytest.mark.parametrize("oiio", [True, False])
def test_3_a_depth_map_of_another_size_is_refused_from_the_headers(tmp_path, monkeypatch, oiio):
    if oiio and not HAVE_OIIO:
        pytest.skip("OpenImageIO not installed")
    image = tmp_path / "image.exr"
    images.write_image(image, np.full((8, 12, 3), 0.5, np.float32))
    data = valid_exr("ZIP", ("Z",), "float", shape=(4, 4), strings={})
    big = tmp_path / "depth.exr"                                   # a 20000 x 20000 header over 4 x 4 pixels
    for name in ("dataWindow", "displayWindow"):
        data = patched(data, value_at(data, name), "<iiii", 0, 0, 19999, 19999)
    big.write_bytes(data)
    small = tmp_path / "small.npy"
    np.save(small, np.ones((8, 11), np.float32))
    no_pixels(monkeypatch)
    with guarded(oiio), pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "available_bytes", lambda: 1 << 50)     # the size alone refuses it
        msg = refused(lambda: image_checks.check_job_inputs("correct", image, big), ImageFileError)
        assert f"{big}: the depth map is 20000 x 20000 px" in msg and f"the image {image} is 12 x 8 px" in msg
        msg = refused(lambda: image_checks.check_job_inputs("bokeh", image, small), ImageFileError)
        assert f"{small}: the depth map is 11 x 8 px" in msg
        image_checks.check_job_inputs("simulate", image, None)


def test_3_a_huge_depth_map_beside_a_small_image_is_refused_from_its_header(tmp_path, monkeypatch):
    image = tmp_path / "image.exr"
    images.write_image(image, np.full((8, 12, 3), 0.5, np.float32))
    depth = tmp_path / "depth.npy"
    with open(depth, "wb") as f:                                     # 20000 x 20000 float32, sparse: no disk used
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (20000, 20000)})
        f.truncate(f.tell() + 4 * 20000 * 20000)
    no_pixels(monkeypatch)
    with guarded():
        msg = refused(lambda: image_checks.check_job_inputs("dof", image, depth), ImageFileError)
    assert "the depth map is 20000 x 20000 px" in msg and "12 x 8 px" in msg


def test_3_a_npy_declaring_more_than_it_holds_is_refused_before_np_load(tmp_path):
    depth = tmp_path / "depth.npy"
    with open(depth, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (4000, 4000)})
        f.write(bytes(64))
    msg = refused(lambda: images.read_depth(depth), ImageFileError)
    assert str(depth) in msg and "declares a 4000 x 4000 array of float64 (128000000 bytes)" in msg


# ------------------------------------------------------------------ 4. malformed attributes
MALFORMED = [                                                   # (id, header change, words of the refusal)
    ("chunkCount of 2 bytes", {"chunkCount": ("int", b"\1\0")}, "'chunkCount' is 'int' of 2 bytes"),
    ("chunkCount negative", {"chunkCount": ("int", struct.pack("<i", -3))}, "'chunkCount' = -3"),
    ("compression of 0 bytes", {"compression": ("compression", b"")}, "'compression' is 'compression' of 0 bytes"),
    ("a box of 15 bytes", {"dataWindow": ("box2i", bytes(15))}, "'dataWindow' is 'box2i' of 15 bytes"),
    ("a box of floats", {"displayWindow": ("box2f", bytes(16))}, "'displayWindow' is 'box2f' of 16 bytes"),
    ("a name that is not a string", {"name": ("int", bytes(4))}, "'name' is 'int' of 4 bytes"),
]


@pytest.mark.parametrize("what, change, words", MALFORMED, ids=[m[0].replace(" ", "_") for m in MALFORMED])
def test_4_a_malformed_attribute_is_one_error_naming_the_file_and_the_attribute(tmp_path, what, change, words):
    path = tmp_path / "bad.exr"
    path.write_bytes(with_header(EXRS[2], change))
    for call in (lambda: rawexr.ExrFile(path), lambda: rawexr.ExrFile(path, header_only=True)):
        msg = refused(call, rawexr.RawExrError)
        assert str(path) in msg and words in msg
    for oiio in (False,):
        with guarded(oiio):
            assert words in refused(lambda: images.read_image(path), ImageFileError)
            assert words in refused(lambda: image_checks.image_size(path), ImageFileError)
    assert words in refused(lambda: cr.read_record(path), cr.CaptureRecordError)


@pytest.mark.parametrize("size", [-1, -2 ** 31, 2 ** 31 - 1, 1 << 30])
def test_4_an_attribute_size_past_the_file_is_one_error_naming_the_attribute(tmp_path, size):
    path = tmp_path / "bad.exr"
    data = EXRS[0]
    path.write_bytes(patched(data, value_at(data, cr.EXR_ATTRIBUTE) - 4, "<i", size))
    for call in (lambda: rawexr.ExrFile(path), lambda: rawexr.ExrFile(path, header_only=True),
                 lambda: cr.read_record(path)):
        msg = refused(call)
        assert str(path) in msg and f"attribute '{cr.EXR_ATTRIBUTE}' of {size} bytes" in msg


# ------------------------------------------------------------------ 5. tiled files: headers and records
@pytest.mark.skipif(not HAVE_OIIO, reason="tiled EXRs are written with OpenImageIO")
def test_5_a_tiled_exr_is_read_with_openimageio_and_its_record_without(tmp_path):
    import OpenImageIO as oiio
    px = np.random.default_rng(3).random((10, 14, 3), dtype=np.float32)
    spec = oiio.ImageSpec(14, 10, 3, oiio.TypeDesc("float"))
    spec.tile_width = spec.tile_height = 8
    spec.attribute(cr.EXR_ATTRIBUTE, RECORD.as_json())
    path = tmp_path / "tiled.exr"
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(path), spec) and out.write_image(px) and out.close()
    np.testing.assert_array_equal(images.read_image(path), px)
    assert cr.read_record(path) == RECORD
    assert image_checks.image_size(path) == (10, 14)
    with guarded(oiio=False):
        assert cr.read_record(path) == RECORD
        assert image_checks.image_size(path) == (10, 14)
        msg = refused(lambda: images.read_image(path), ImageFileError)
        assert "part 0 is a tiled image" in msg and "pip install OpenImageIO" in msg
        assert "tiledimage" in refused(lambda: image_checks.image_size(path, pixels=True), ImageFileError)


# ------------------------------------------------------------------ 6. records
def test_6_a_record_nested_deep_is_one_capture_record_error(tmp_path):
    """30000 levels (60 KB, within the size limit; json's recursion ends at
    about 1000) and 100000 (200 KB: refused for its size first)."""
    side = cr.sidecar_path(tmp_path / "a.png")
    side.write_text("[" * 30_000 + "]" * 30_000)
    msg = refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    assert str(side) in msg and f"nested more than {cr.RECORD_MAX_DEPTH} levels" in msg
    path = tmp_path / "deep.exr"
    path.write_bytes(valid_exr("ZIP", ("Z",), "float", strings={cr.EXR_ATTRIBUTE: "{" * 30_000}))
    assert "nested more than" in refused(lambda: cr.read_record(path), cr.CaptureRecordError)
    side.write_text("[" * 100_000 + "]" * 100_000)
    assert "200000 bytes" in refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    nested = '{"a": "[[[[\\"{{{{", "b": [[[1]]]}'                   # brackets in strings do not count
    assert cr.CaptureRecord.from_json(json.dumps({"format": 1, "kind": "simulated", "extra": json.loads(nested)}),
                                      side).extra["b"] == [[[1]]]


def test_6_a_sidecar_of_1_gib_is_refused_before_it_is_read(tmp_path):
    side = cr.sidecar_path(tmp_path / "a.png")
    with open(side, "wb") as f:
        f.truncate(1 << 30)                                         # sparse: no disk used
    msg = refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    assert str(side) in msg and "1073741824 bytes; a record is at most 65536 bytes (64 KiB)" in msg


def test_6_a_sidecar_that_is_a_folder_is_refused(tmp_path):
    side = cr.sidecar_path(tmp_path / "a.png")
    side.mkdir()
    msg = refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    assert str(side) in msg and "is a folder" in msg


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_6_a_sidecar_that_is_a_fifo_is_refused_without_blocking(tmp_path):
    side = cr.sidecar_path(tmp_path / "a.png")
    os.mkfifo(side)
    assert "not a regular file" in refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)


def test_6_a_huge_exr_record_attribute_is_refused(tmp_path):
    """A record that is valid JSON but longer than RECORD_MAX_BYTES (100 KB of extra facts)."""
    big = cr.CaptureRecord(kind="simulated", extra={"pad": "x" * 100_000}, software="dcdi test")
    path = tmp_path / "big.exr"
    path.write_bytes(valid_exr("ZIP", ("Z",), "float", strings={cr.EXR_ATTRIBUTE: big.as_json()}))
    msg = refused(lambda: cr.read_record(path), cr.CaptureRecordError)
    assert str(path) in msg and "characters; a record is at most 65536 (64 KiB)" in msg


@pytest.mark.parametrize("field, value", [("axis_px", [1.0]), ("focus_distance_m", -2), ("pixel_pitch_mm", "12"),
                                          ("noise.full_well_electrons", 0), ("focus_distance_m", 10 ** 400),
                                          ("kind", None)],
                         ids=["axis_px", "focus_negative", "pitch_text", "full_well", "focus_400_digits", "no_kind"])
def test_6_a_bad_field_is_named_as_the_records_field_with_the_file(tmp_path, field, value):
    d = json.loads(RECORD.as_json())
    if field == "noise.full_well_electrons":
        d["noise"] = {"full_well_electrons": value, "read_noise_electrons": 1.0, "seed": 1}
    elif value is None:
        del d[field]
    else:
        d[field] = value
    side = cr.sidecar_path(tmp_path / "a.png")
    side.write_text(json.dumps(d))
    msg = refused(lambda: cr.read_record(tmp_path / "a.png"), cr.CaptureRecordError)
    assert msg.startswith(f"{side}: capture record: field {field} ") and "allowed: " in msg, msg


# ------------------------------------------------------------------ 7. PNG and JPEG headers
def png_of_size(tmp_path, h, w) -> Path:
    """A valid 8 x 12 PNG whose IHDR (CRC fixed) declares ``h`` x ``w`` px."""
    if not HAVE_OIIO:
        pytest.skip("PNG is written with OpenImageIO")
    good = valid_image(".png", str(tmp_path))
    path = tmp_path / "huge.png"
    path.write_bytes(crc_fixed_png(patched(good, 16, ">II", w, h)))
    return path


@pytest.mark.parametrize("oiio", [True, False])
def test_7_a_png_declaring_a_huge_size_is_refused_by_the_guard_from_its_header(tmp_path, monkeypatch, oiio):
    path = png_of_size(tmp_path, 20000, 20000)
    with guarded(oiio):
        assert image_checks.image_size(path) == (20000, 20000)
        msg = refused(lambda: image_checks.check_job_inputs("simulate", path), MemoryLimitError)
        assert f"the image {path}: 20000 x 20000 px" in msg
        if oiio:
            msg = refused(lambda: images.read_image(path), MemoryLimitError)
            assert str(path) in msg and "20000 x 20000 px" in msg


@pytest.mark.skipif(not HAVE_OIIO, reason="PNG is written with OpenImageIO")
def test_7_a_truncated_png_is_one_image_file_error(tmp_path, capfd):
    good = valid_image(".png", str(tmp_path))
    path = tmp_path / "cut.png"
    path.write_bytes(good[:len(good) // 2])
    msg = refused(lambda: images.read_image(path), ImageFileError)
    assert str(path) in msg and capfd.readouterr().err == ""         # libpng's own line is not printed
    path.write_bytes(good[:20])                                    # cut inside the IHDR
    with guarded(oiio=False):
        assert "cannot be read as a PNG or JPEG" in refused(lambda: image_checks.image_size(path), ImageFileError)


@pytest.mark.skipif(not HAVE_OIIO, reason="JPEG is written with OpenImageIO")
def test_7_a_jpeg_segment_of_size_0_is_refused(tmp_path):
    good = valid_image(".jpg", str(tmp_path))
    path = tmp_path / "loop.jpg"
    path.write_bytes(good[:4] + b"\0\0" + good[6:])                # the first segment's size: 0
    with guarded(oiio=False):
        assert "cannot be read as a PNG or JPEG" in refused(lambda: image_checks.image_size(path), ImageFileError)
