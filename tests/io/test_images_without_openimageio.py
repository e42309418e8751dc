"""dcdi_core.io.images where OpenImageIO does not import (blocked here as a
distribution's Blender lacks it: sys.modules['OpenImageIO'] = None): EXR
and .npy through rawexr with the same results and messages as with
OpenImageIO, and a one-line refusal naming the file for what needs it."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

oiio = pytest.importorskip("OpenImageIO")

from dcdi_core.errors import DatasetError  # noqa: E402
from dcdi_core.io.image_checks import check_image_output, image_size  # noqa: E402
from dcdi_core.io.image_file import ImageFileError, have_openimageio  # noqa: E402
from dcdi_core.io.images import read_depth, read_image, write_depth, write_image  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture
def no_oiio(monkeypatch):
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    assert not have_openimageio()


def _both(monkeypatch, fn):
    """fn() with OpenImageIO, then without: (result or error text) twice."""
    def once():
        try:
            return fn()
        except ImageFileError as e:
            assert "\n" not in str(e)
            return f"ImageFileError: {e}"
    with_it = once()
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "OpenImageIO", None)
        without = once()
    return with_it, without


def _same(a, b):
    if isinstance(a, str) or isinstance(b, str):
        assert a == b
    else:
        assert a.dtype == b.dtype == np.float32
        np.testing.assert_array_equal(a, b)


def _write(path, pixels, names, typename="float", window=None, compression="zip"):
    pixels = np.ascontiguousarray(pixels, np.float32)
    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, oiio.TypeDesc(typename))
    spec.channelnames = tuple(names)
    spec.attribute("compression", compression)
    if window:
        spec.x, spec.y, spec.full_x, spec.full_y, spec.full_width, spec.full_height = window
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(path), spec) and out.write_image(pixels) and out.close(), out.geterror()
    return path


def _fixtures(tmp_path) -> dict[str, Path]:
    """EXR files exercising the colour and depth rules (one each)."""
    rng = np.random.default_rng(0)

    def px(c, h=5, w=7):
        return (rng.standard_normal((h, w, c)) * 3).astype(np.float32)

    f = {}
    f["rgb"] = _write(tmp_path / "rgb.exr", px(3), "RGB")
    f["rgba-z"] = _write(tmp_path / "rgbaz.exr", px(5), ["R", "G", "B", "A", "Z"], compression="none")
    f["half"] = _write(tmp_path / "half.exr", px(3), "RGB", "half", compression="zips")
    f["grey-y"] = _write(tmp_path / "y.exr", px(1), ["Y"])
    f["lower-case"] = _write(tmp_path / "lc.exr", px(4), ["r", "g", "b", "z"])
    names = ["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B", "ViewLayer.Combined.A",
             "ViewLayer.Normal.X", "ViewLayer.Normal.Y", "ViewLayer.Normal.Z", "ViewLayer.Depth.Z"]
    f["layers"] = _write(tmp_path / "layers.exr", px(8), names)
    f["two-layers"] = _write(tmp_path / "two.exr", px(6), ["Diffuse.R", "Diffuse.G", "Diffuse.B", "Image.R",
                                                           "Image.G", "Image.B"])
    f["depth-only"] = _write(tmp_path / "z.exr", px(1), ["Z"])
    f["depth-v"] = _write(tmp_path / "v.exr", px(2), ["Depth.V", "N.X"])
    f["no-depth"] = _write(tmp_path / "n.exr", px(2), ["foo", "bar"])
    f["window-inside"] = _write(tmp_path / "win.exr", px(3, 2, 2), "RGB", window=(1, 1, 0, 0, 4, 3))
    f["window-outside"] = _write(tmp_path / "wout.exr", px(3, 6, 8), "RGB", window=(-2, -1, 0, 0, 4, 3))
    f["blender-none"] = DATA / "blender-5.2-multilayer-none.exr"
    f["blender-zip"] = DATA / "blender-5.2-multilayer-zip.exr"
    f["blender-zip-half"] = DATA / "blender-5.2-multilayer-zip-half.exr"
    f["blender-zips"] = DATA / "blender-5.2-multilayer-zips.exr"
    return f


CASES = ["rgb", "rgba-z", "half", "grey-y", "lower-case", "layers", "two-layers", "depth-only", "depth-v",
         "no-depth", "window-inside", "window-outside", "blender-none", "blender-zip", "blender-zip-half",
         "blender-zips"]


@pytest.mark.parametrize("case", CASES)
def test_reads_equal_those_with_openimageio(tmp_path, monkeypatch, case):
    """The same arrays, or the same error message, with and without OpenImageIO."""
    path = _fixtures(tmp_path)[case]
    _same(*_both(monkeypatch, lambda: read_image(path)))
    _same(*_both(monkeypatch, lambda: read_depth(path)))
    for channel in ("Z", "G", "ViewLayer.Depth.Z", "nope", "depth.z"):
        _same(*_both(monkeypatch, lambda: read_depth(path, channel=channel)))


def test_multipart_choice_and_messages_equal_those_with_openimageio(tmp_path, monkeypatch):
    """Several parts with a bare 'Z' each: the same refusal, the same choice by part name."""
    h, w = 4, 6
    specs, pixels = [], []
    for name, chans in (("rgba", ("R", "G", "B")), ("Layer1.Depth", ("Z",)), ("Layer2.Depth", ("Z",))):
        spec = oiio.ImageSpec(w, h, len(chans), oiio.TypeDesc("float"))
        spec.channelnames = chans
        spec.attribute("name", name)
        spec.attribute("compression", "zip")
        specs.append(spec)
        pixels.append(np.random.default_rng(len(specs)).random((h, w, len(chans)), dtype=np.float32))
    path = tmp_path / "mp.exr"
    out = oiio.ImageOutput.create("openexr")
    assert out.open(str(path), specs)
    for k, (spec, p) in enumerate(zip(specs, pixels)):
        if k:
            assert out.open(str(path), spec, "AppendSubimage")
        assert out.write_image(p)
    out.close()
    with_it, without = _both(monkeypatch, lambda: read_depth(path))
    assert "several channels match depth channel 'Z'" in without and with_it == without
    for channel in ("Layer2.Depth.Z", "layer1.depth.z", "depth.Z"):
        _same(*_both(monkeypatch, lambda: read_depth(path, channel=channel)))
    _same(*_both(monkeypatch, lambda: read_image(path)))


def test_uint_channels_as_openimageio_reads_them(tmp_path, monkeypatch):
    from dcdi_core.io import rawexr
    u = np.array([[0, 1, 2 ** 31, 2 ** 32 - 1]], np.uint32)
    path = tmp_path / "u.exr"
    rawexr.write_exr(path, {"R": u, "G": u, "B": u, "Z": u}, pixel_type="uint")
    _same(*_both(monkeypatch, lambda: read_image(path)))
    with_it, without = _both(monkeypatch, lambda: read_depth(path))
    assert "holds uint values; depth must be stored as floating-point metres" in without and with_it == without


def test_writes_read_back_by_openimageio_and_leave_no_temporary(tmp_path, no_oiio):
    rng = np.random.default_rng(1)
    img = (rng.standard_normal((21, 18, 3)) * 40).astype(np.float32)
    d = np.array([[1.5, np.inf, np.nan], [0.0, -1.0, 1e10]], np.float32)
    write_image(tmp_path / "a.exr", img)
    write_image(tmp_path / "h.exr", img, bit_depth=16)
    write_depth(tmp_path / "d.exr", d)
    write_depth(tmp_path / "d.npy", d)
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "d.exr", "d.npy", "h.exr"]
    for name, want, fmt, chans in (("a.exr", img, "float", ("R", "G", "B")),
                                   ("h.exr", img.astype(np.float16).astype(np.float32), "half", ("R", "G", "B")),
                                   ("d.exr", d[..., None], "float", ("Z",))):
        inp = oiio.ImageInput.open(str(tmp_path / name))
        spec = inp.spec()
        assert spec.channelnames == chans and spec.format == oiio.TypeDesc(fmt)
        assert spec.getattribute("compression") == "zip"
        np.testing.assert_array_equal(np.asarray(inp.read_image(0, 0, 0, len(chans), "float")), want)
        inp.close()
        back = read_image(tmp_path / name) if name != "d.exr" else read_depth(tmp_path / name)
        np.testing.assert_array_equal(back, want if name != "d.exr" else d)
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy"), d)


def test_writes_are_deterministic_and_refuse_what_openimageio_would(tmp_path, no_oiio):
    img = np.linspace(0, 3, 4 * 32 * 3, dtype=np.float32).reshape(4, 32, 3)
    write_image(tmp_path / "a.exr", img)
    write_image(tmp_path / "b.exr", img)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    img[1, 2, 0] = np.nan
    with pytest.raises(ImageFileError, match=r"c.exr.*non-finite.*row 1, column 2, channel R"):
        write_image(tmp_path / "sub" / "c.exr", img)
    with pytest.raises(ImageFileError, match="half-float range"):
        write_image(tmp_path / "big.exr", np.full((2, 2, 3), 7e4, np.float32), bit_depth=16)
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "b.exr"]


@pytest.mark.parametrize("name", ["out.png", "out.jpg"])
def test_png_and_jpeg_are_refused_in_one_line_naming_the_file(tmp_path, monkeypatch, name):
    img = np.full((4, 4, 3), 0.5, np.float32)
    write_image(tmp_path / name, img)                           # with OpenImageIO: written
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    for call in (lambda: write_image(tmp_path / "new" / name, img), lambda: check_image_output(tmp_path / name),
                 lambda: read_image(tmp_path / name)):
        with pytest.raises(ImageFileError) as info:
            call()
        msg = str(info.value)
        assert "\n" not in msg and name in msg and "pip install OpenImageIO" in msg
    assert not (tmp_path / "new").exists()


def test_compressions_rawexr_cannot_read_are_refused_naming_what_to_install(no_oiio):
    path = DATA / "blender-5.2-multilayer-piz-half.exr"
    for call in (lambda: read_image(path), lambda: read_depth(path)):
        with pytest.raises(ImageFileError) as info:
            call()
        msg = str(info.value)
        assert "\n" not in msg and path.name in msg and "PIZ" in msg and "pip install OpenImageIO" in msg
    assert image_size(path) == (21, 37)                         # its header is read all the same
    with pytest.raises(ImageFileError, match="PIZ"):
        image_size(path, pixels=True)


def test_missing_and_damaged_files_name_the_file(tmp_path, no_oiio):
    for reader in (read_image, read_depth):
        with pytest.raises(ImageFileError, match="missing.exr: file not found"):
            reader(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_text("not an image")
    with pytest.raises(ImageFileError, match="junk.exr: cannot be read without OpenImageIO"):
        read_image(tmp_path / "junk.exr")
    from dcdi_core.io import rawexr
    good = DATA / "blender-5.2-multilayer-zip.exr"
    data = bytearray(good.read_bytes())
    data[int(rawexr.ExrFile(good)._tables[0][0]) + 12 + 30] ^= 0xFF        # in the Combined part's first chunk
    (tmp_path / "bad.exr").write_bytes(bytes(data))
    with pytest.raises(ImageFileError) as info:
        read_image(tmp_path / "bad.exr")
    msg = str(info.value)
    assert "\n" not in msg and "bad.exr" in msg and ("corrupt" in msg or "damaged" in msg)


def test_image_size_from_headers_equals_openimageio(tmp_path, monkeypatch):
    img = np.random.default_rng(2).random((13, 29, 3), dtype=np.float32)
    for name in ("a.png", "a.jpg", "a.exr"):
        write_image(tmp_path / name, img)
        with_it, without = _both(monkeypatch, lambda: image_size(tmp_path / name))
        assert with_it == without == (13, 29)
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    with pytest.raises(ImageFileError, match="a.png.*pip install OpenImageIO"):
        image_size(tmp_path / "a.png", pixels=True)
    assert image_size(tmp_path / "a.exr", pixels=True) == (13, 29)


def test_texture_folders_are_checked_by_who_decodes_them(tmp_path, monkeypatch):
    """Blender decodes the Blender recipes' PNGs itself; the numpy recipe
    needs OpenImageIO for them, and is refused before any work without it."""
    from dcdi_core.dataset.textures import TextureLibrary
    write_image(tmp_path / "photo.png", np.full((8, 8, 3), 0.3, np.float32))
    write_image(tmp_path / "wall.exr", np.full((8, 8, 3), 0.3, np.float32))
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    assert len(TextureLibrary.from_folder(tmp_path).sets) == 2
    with pytest.raises(DatasetError, match=r"--textures: .*photo.png.*pip install OpenImageIO"):
        TextureLibrary.from_folder(tmp_path, pixels=True)
    os.remove(tmp_path / "photo.png")
    assert len(TextureLibrary.from_folder(tmp_path, pixels=True).sets) == 1


def test_a_png_depth_map_is_refused_naming_what_to_install(tmp_path, monkeypatch):
    from dcdi_core.dataset.rgbd import read_any_depth
    spec = oiio.ImageSpec(3, 2, 1, oiio.TypeDesc("uint16"))
    out = oiio.ImageOutput.create("png")
    assert out.open(str(tmp_path / "d.png"), spec) and out.write_image(np.full((2, 3, 1), 1500, np.uint16))
    out.close()
    np.testing.assert_array_equal(read_any_depth(tmp_path / "d.png"), np.full((2, 3), 1.5, np.float32))
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    with pytest.raises(ImageFileError, match=r"d.png: a PNG depth map cannot be read without OpenImageIO"):
        read_any_depth(tmp_path / "d.png")
