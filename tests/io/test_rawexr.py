"""dcdi_core.io.rawexr, the numpy EXR reader and writer, against OpenImageIO:
what one writes the other reads, exactly (NONE, ZIPS, ZIP; FLOAT, HALF;
one part and Blender's multi-part layout), the same pixels give the same
bytes, and a damaged or unsupported file is refused in one line."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

oiio = pytest.importorskip("OpenImageIO")

from dcdi_core.io import rawexr  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
BLENDER_FILES = sorted(p.name for p in DATA.glob("blender-5.2-multilayer-*.exr") if "piz" not in p.name)


def _values(h, w, seed=0, half=False):
    """Smooth areas (blocks zlib shrinks), noise (blocks stored raw) and the
    awkward values: +-inf, NaN, -0, subnormals, the largest finite."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    v = np.where(yy < h / 2, np.sin(xx / 3) * 2 + yy / 7, rng.standard_normal((h, w)) * 1e3).astype(np.float32)
    flat = v.reshape(-1)
    big = 65504.0 if half else 3.4028235e38
    tiny = 6e-8 if half else 1e-42
    special = np.array([np.inf, -np.inf, np.nan, -0.0, tiny, -tiny, big, -big], np.float32)
    flat[:min(flat.size, special.size)] = special[:flat.size]
    return v.astype(np.float16).astype(np.float32) if half else v


def _oiio_write(path, channels: dict, typename="float", compression="zip", parts=None):
    """One part ({name: (h, w)}) or several ([(part name, {name: (h, w)})]) with OpenImageIO."""
    parts = parts or [(None, channels)]
    specs, pixels = [], []
    for name, chans in parts:
        names = list(chans)
        h, w = chans[names[0]].shape
        spec = oiio.ImageSpec(w, h, len(names), oiio.TypeDesc(typename))
        spec.channelnames = tuple(names)
        spec.attribute("compression", compression)
        if name:
            spec.attribute("name", name)
        specs.append(spec)
        pixels.append(np.stack([chans[n] for n in names], -1).astype(np.float32))
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(path), specs if len(specs) > 1 else specs[0]), out.geterror()
    for k, (spec, px) in enumerate(zip(specs, pixels)):
        if k:
            assert out.open(str(path), spec, "AppendSubimage"), out.geterror()
        assert out.write_image(np.ascontiguousarray(px)), out.geterror()
    assert out.close(), out.geterror()


def _oiio_read(path) -> list[tuple[str, dict]]:
    """[(part name, {channel: (h, w) float32})] as OpenImageIO reads them."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    out, s = [], 0
    try:
        while inp.seek_subimage(s, 0):
            spec = inp.spec(s, 0)
            px = np.asarray(inp.read_image(s, 0, 0, spec.nchannels, "float"), np.float32).reshape(
                spec.height, spec.width, spec.nchannels)
            out.append((spec.getattribute("oiio:subimagename") or "",
                        {n: px[..., i] for i, n in enumerate(spec.channelnames)}))
            s += 1
    finally:
        inp.close()
    return out


def _assert_same_as_oiio(path):
    f = rawexr.ExrFile(path)
    ref = _oiio_read(path)
    assert [p.name for p in f.parts] == [name for name, _ in ref]
    for p, (_, chans) in zip(f.parts, ref):
        mine = f.read(p.index)
        assert sorted(mine) == sorted(chans)
        for n, a in chans.items():
            assert mine[n].dtype == np.float32 and mine[n].shape == a.shape
            np.testing.assert_array_equal(mine[n], a, err_msg=f"{path.name} {p.label} {n}")  # NaN where NaN
    return f


# ---------------------------------------------------------------- reading what OpenImageIO writes

@pytest.mark.parametrize("compression", ["none", "zips", "zip"])
@pytest.mark.parametrize("typename", ["float", "half"])
@pytest.mark.parametrize("shape", [(1, 1), (16, 5), (21, 37), (35, 18)])
def test_reads_what_openimageio_writes(tmp_path, compression, typename, shape):
    h, w = shape
    chans = {n: _values(h, w, seed=k, half=typename == "half") for k, n in enumerate(["R", "G", "B", "A", "Z"])}
    path = tmp_path / "o.exr"
    _oiio_write(path, chans, typename, compression)
    f = _assert_same_as_oiio(path)
    assert f.parts[0].compression_name == compression.upper()
    for n, a in chans.items():
        np.testing.assert_array_equal(f.read()[n], a)


def test_reads_mixed_channel_types(tmp_path):
    h, w = 19, 7
    spec = oiio.ImageSpec(w, h, 3, oiio.TypeDesc("float"))
    spec.channelnames = ("R", "G", "Z")
    spec.channelformats = (oiio.TypeDesc("half"), oiio.TypeDesc("half"), oiio.TypeDesc("float"))
    spec.attribute("compression", "zip")
    px = np.stack([_values(h, w, 1, half=True), _values(h, w, 2, half=True), _values(h, w, 3)], -1)
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(tmp_path / "m.exr"), spec) and out.write_image(px) and out.close()
    f = _assert_same_as_oiio(tmp_path / "m.exr")
    assert [c.type_name for c in f.parts[0].channels] == ["half", "half", "float"]       # G, R, Z in name order


@pytest.mark.parametrize("compression", ["none", "zip"])
def test_reads_multipart_files_laid_out_as_blender_writes_them(tmp_path, compression):
    """Blender 5's multilayer EXR: one part per pass, named '<view layer>.<pass>'."""
    h, w = 23, 31
    layer = "ViewLayer"
    parts = [(f"{layer}.Combined", {f"{layer}.Combined.{c}": _values(h, w, k) for k, c in enumerate("RGBA")}),
             (f"{layer}.Depth", {f"{layer}.Depth.Z": _values(h, w, 7)}),
             (f"{layer}.Normal", {f"{layer}.Normal.{c}": _values(h, w, 8 + k) for k, c in enumerate("XYZ")})]
    path = tmp_path / "ml.exr"
    _oiio_write(path, None, "float", compression, parts=parts)
    f = _assert_same_as_oiio(path)
    assert f.multipart and [p.name for p in f.parts] == [name for name, _ in parts]
    merged = rawexr.read_exr_channels(path)
    np.testing.assert_array_equal(merged[f"{layer}.Depth.Z"], parts[1][1][f"{layer}.Depth.Z"])


@pytest.mark.parametrize("name", BLENDER_FILES)
def test_reads_the_files_blender_5_2_wrote(name):
    """Renders Blender 5.2.2 saved (a cube, 37 x 21, Combined, Depth, Normal
    passes): uncompressed, ZIPS, ZIP and ZIP at half float."""
    f = _assert_same_as_oiio(DATA / name)
    assert [p.name for p in f.parts] == ["ViewLayer.Combined", "ViewLayer.Depth", "ViewLayer.Normal"]
    assert f.read(0)["ViewLayer.Combined.R"].std() > 0


# ---------------------------------------------------------------- OpenImageIO reading what rawexr writes

@pytest.mark.parametrize("compression", ["NONE", "ZIPS", "ZIP"])
@pytest.mark.parametrize("ptype", ["float", "half"])
@pytest.mark.parametrize("shape", [(1, 1), (17, 3), (40, 29)])
def test_openimageio_reads_what_rawexr_writes(tmp_path, compression, ptype, shape):
    h, w = shape
    long_name = "ViewLayer.AVeryLongPassName.ForTheLongNamesFlag.Z"          # > 31 bytes
    chans = {n: _values(h, w, seed=k, half=ptype == "half") for k, n in enumerate(["R", "G", "B", "Z", long_name])}
    path = tmp_path / "r.exr"
    rawexr.write_exr(path, chans, pixel_type=ptype, compression=compression)
    (name, got), = _oiio_read(path)
    assert name == "" and sorted(got) == sorted(chans)
    for n, a in chans.items():
        np.testing.assert_array_equal(got[n], a, err_msg=n)
    inp = oiio.ImageInput.open(str(path))
    assert inp.spec().getattribute("compression") == compression.lower()
    assert inp.spec().format == oiio.TypeDesc(ptype)
    inp.close()
    for n, a in rawexr.ExrFile(path).read().items():
        np.testing.assert_array_equal(a, chans[n])


def test_half_is_rounded_as_openimageio_rounds_it(tmp_path):
    """float32 values written as half: the same halves as OpenImageIO's own conversion."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.standard_normal(4000) * 10.0 ** rng.integers(-9, 5, 4000),
                        np.float32([65504.0, 65519.0, 6.1e-5, 5.96e-8, 2.9e-8, 1.0 + 2 ** -11, 1.0 + 3 * 2 ** -11])])
    x = x.astype(np.float32).reshape(1, -1)
    _oiio_write(tmp_path / "o.exr", {"Y": x}, "half", "none")
    rawexr.write_exr(tmp_path / "r.exr", {"Y": x}, pixel_type="half", compression="NONE")
    np.testing.assert_array_equal(_oiio_read(tmp_path / "r.exr")[0][1]["Y"], _oiio_read(tmp_path / "o.exr")[0][1]["Y"])


def test_incompressible_chunks_are_stored_raw_and_read_back(tmp_path):
    """Noise that zlib cannot shrink is stored raw (the byte count tells the reader)."""
    rng = np.random.default_rng(3)
    noise = {c: rng.random((32, 50), dtype=np.float32) for c in "RGB"}
    smooth = {c: np.zeros((32, 50), np.float32) for c in "RGB"}
    for chans in (noise, smooth):
        path = tmp_path / "n.exr"
        data = rawexr.encode_exr(chans)
        path.write_bytes(data)
        f = rawexr.ExrFile(path)
        raw_block = 16 * 3 * 50 * 4
        sizes = [struct.unpack_from("<i", data, int(off) + 4)[0] for off in f._tables[0]]
        assert (all(s == raw_block for s in sizes) if chans is noise else all(s < raw_block for s in sizes))
        for n, a in _oiio_read(path)[0][1].items():
            np.testing.assert_array_equal(a, chans[n])
            np.testing.assert_array_equal(f.read()[n], chans[n])


def test_same_pixels_give_the_same_bytes():
    chans = {c: _values(33, 21, k) for k, c in enumerate("RGB")}
    a = rawexr.encode_exr(chans)
    assert a == rawexr.encode_exr({c: chans[c].copy() for c in "BGR"})            # any dict order
    assert a != rawexr.encode_exr({**chans, "R": chans["R"] + 1})
    assert rawexr.encode_exr(chans, pixel_type="half") == rawexr.encode_exr(chans, pixel_type="half")
    assert b"capDate" not in a and b"DateTime" not in a                           # no time stamp


def test_chunks_deflated_on_the_thread_pool_give_the_bytes_of_one_thread(monkeypatch):
    big = {c: _values(200, 700, k) for k, c in enumerate("RGB")}                   # 1.7 MB: on the pool
    pooled = rawexr.encode_exr(big)
    monkeypatch.setattr(rawexr, "_PARALLEL_BYTES", 1 << 40)
    assert rawexr.encode_exr(big) == pooled


# ---------------------------------------------------------------- what is refused

def _zip_file(tmp_path, h=40, w=9):
    path = tmp_path / "z.exr"
    rawexr.write_exr(path, {c: _values(h, w, k) for k, c in enumerate("RGB")})
    return path, bytearray(path.read_bytes()), rawexr.ExrFile(path)


def _one_line_error(path, match):
    with pytest.raises(rawexr.RawExrError, match=match) as info:
        rawexr.ExrFile(path).read()
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    return str(info.value)


def test_a_corrupt_chunk_is_refused_in_one_line(tmp_path):
    path, data, f = _zip_file(tmp_path)
    second = int(f._tables[0][1])
    data[second + 8 + 20] ^= 0xFF                      # inside the second chunk's zlib stream
    path.write_bytes(bytes(data))
    msg = _one_line_error(path, r"scanlines 16\.\.31\) is corrupt|decompresses to")
    assert "part 0" in msg


def test_a_truncated_file_is_refused(tmp_path):
    path, data, f = _zip_file(tmp_path)
    path.write_bytes(bytes(data[:int(f._tables[0][-1]) + 10]))
    _one_line_error(path, "runs past the end of the file")
    path.write_bytes(bytes(data[:100]))
    with pytest.raises(rawexr.RawExrError, match="truncated"):
        rawexr.ExrFile(path)


def test_a_damaged_offset_table_is_refused(tmp_path):
    path, data, f = _zip_file(tmp_path)
    at = f._chunks_start - 8 * len(f._tables[0])
    data[at + 8:at + 16] = data[at:at + 8]             # two entries for the first block, none for the second
    path.write_bytes(bytes(data))
    _one_line_error(path, "starts at scanline 0, not at a block")
    data[at + 8:at + 16] = struct.pack("<Q", len(data) + 5)
    path.write_bytes(bytes(data))
    _one_line_error(path, "outside the file")


def test_not_an_exr_and_unread_layouts_are_refused_by_name(tmp_path):
    (tmp_path / "t.exr").write_bytes(b"\0" * 64)
    with pytest.raises(rawexr.RawExrError, match="not an OpenEXR file"):
        rawexr.read_exr_channels(tmp_path / "t.exr")
    for comp, name in (("piz", "PIZ"), ("rle", "RLE"), ("dwaa", "DWAA"), ("pxr24", "PXR24")):
        _oiio_write(tmp_path / f"{comp}.exr", {"R": _values(20, 8)}, "float", comp)
        _one_line_error(tmp_path / f"{comp}.exr", f"compressed with {name}; only NONE, ZIPS and ZIP")
    _one_line_error(DATA / "blender-5.2-multilayer-piz-half.exr", "part 0 'ViewLayer.Combined' is compressed with PIZ")
    spec = oiio.ImageSpec(8, 8, 1, oiio.TypeDesc("float"))
    spec.tile_width = spec.tile_height = 4
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(tmp_path / "tiled.exr"), spec) and out.write_image(np.zeros((8, 8, 1), np.float32))
    out.close()
    head = rawexr.ExrFile(tmp_path / "tiled.exr", header_only=True)     # its header is read all the same
    assert head.parts[0].kind == "tiledimage" and head.parts[0].data_window == (0, 0, 7, 7)
    _one_line_error(tmp_path / "tiled.exr", r"part 0 is a tiled image \(type 'tiledimage'\)")


def test_the_writer_refuses_what_it_cannot_write(tmp_path):
    with pytest.raises(rawexr.RawExrError, match="only NONE, ZIPS and ZIP are written"):
        rawexr.encode_exr({"R": np.zeros((2, 2), np.float32)}, compression="PIZ")
    with pytest.raises(rawexr.RawExrError, match="shape"):
        rawexr.encode_exr({"R": np.zeros((2, 2), np.float32), "G": np.zeros((2, 3), np.float32)})
    with pytest.raises(rawexr.RawExrError, match="pixel type"):
        rawexr.encode_exr({"R": np.zeros((2, 2), np.float32)}, pixel_type="double")
