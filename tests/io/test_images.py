"""Image and depth file I/O (dcdi_core.io.images, image_file)."""
from __future__ import annotations

import os

import numpy as np
import pytest

oiio = pytest.importorskip("OpenImageIO")

from dcdi_core.io.image_file import ImageFileError  # noqa: E402
from dcdi_core.io.images import (  # noqa: E402
    linear_to_srgb,
    read_depth,
    read_image,
    srgb_to_linear,
    write_depth,
    write_image,
)
from dcdi_core.errors import DcdiError  # noqa: E402


def _gradient(h=16, w=256):
    ramp = np.linspace(0.0, 1.0, w, dtype=np.float32)
    img = np.empty((h, w, 3), np.float32)
    img[..., 0] = ramp
    img[..., 1] = ramp[::-1]
    img[..., 2] = (ramp ** 2.2)[None, :] * np.linspace(0.2, 1.0, h, dtype=np.float32)[:, None]
    return img


def _oiio_write(path, pixels, typename, channelnames=None, unassociated=False, window=None):
    """Write raw pixels (h, w, c) with OpenImageIO, bypassing the module."""
    pixels = np.ascontiguousarray(pixels)
    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, oiio.TypeDesc(typename))
    if channelnames:
        spec.channelnames = tuple(channelnames)
    if unassociated:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    if window:
        spec.x, spec.y, spec.full_x, spec.full_y, spec.full_width, spec.full_height = window
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(pixels), out.geterror()
    assert out.close()


def _listing(folder):
    return sorted(os.listdir(folder))


# ---------------------------------------------------------------- sRGB curve

def test_srgb_functions_are_inverse_and_piecewise():
    x = np.linspace(-0.1, 1.5, 20001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)
    # standard breakpoints: linear segment up to 0.04045 (encoded) / 0.0031308 (linear)
    assert srgb_to_linear(0.04045) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    assert srgb_to_linear(0.0405) == pytest.approx(((0.0405 + 0.055) / 1.055) ** 2.4, rel=1e-12)
    assert linear_to_srgb(0.0031308) == pytest.approx(12.92 * 0.0031308, rel=1e-12)
    assert linear_to_srgb(0.0032) == pytest.approx(1.055 * 0.0032 ** (1 / 2.4) - 0.055, rel=1e-12)
    # the two segments meet (continuity at the breakpoints)
    assert linear_to_srgb(0.04045 / 12.92) == pytest.approx(0.04045, abs=1e-7)
    assert srgb_to_linear(0.5) == pytest.approx(0.21404114, abs=1e-7)
    assert linear_to_srgb(0.18) == pytest.approx(0.46135613, abs=1e-7)
    assert srgb_to_linear(0.0) == 0.0 and srgb_to_linear(1.0) == pytest.approx(1.0, abs=1e-15)


def test_srgb_functions_keep_float32_and_nan():
    x = np.array([[0.0, 0.5, np.nan]], np.float32)
    y = srgb_to_linear(x)
    assert y.dtype == np.float32 and y.shape == x.shape and np.isnan(y[0, 2])
    assert linear_to_srgb(x).dtype == np.float32


# ---------------------------------------------------------------- images

def test_png_8bit_round_trip_within_one_code(tmp_path):
    img = _gradient()
    path = tmp_path / "g.png"
    write_image(path, img)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    back = read_image(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    err = np.abs(linear_to_srgb(back.astype(np.float64)) - linear_to_srgb(img.astype(np.float64)))
    assert err.max() <= 0.5 / 255 + 1e-6
    assert _listing(tmp_path) == ["g.png"]  # no temporary left behind


def test_png_16bit_round_trip(tmp_path):
    img = _gradient(8, 1024)
    path = tmp_path / "g16.png"
    write_image(path, img, bit_depth=16)
    inp = oiio.ImageInput.open(str(path))
    assert inp.spec().format == oiio.TypeDesc("uint16")
    inp.close()
    back = read_image(path)
    err = np.abs(linear_to_srgb(back.astype(np.float64)) - linear_to_srgb(img.astype(np.float64)))
    assert err.max() <= 1 / 65535


def test_png_clips_to_unit_range(tmp_path):
    img = np.array([[[-0.5, 0.5, 7.0]]], np.float32)
    write_image(tmp_path / "c.png", img)
    back = read_image(tmp_path / "c.png")
    assert back[0, 0, 0] == 0.0 and back[0, 0, 2] == pytest.approx(1.0)


def test_exr_float32_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    img = (rng.standard_normal((9, 13, 3)) * 50).astype(np.float32)  # > 1 and < 0 too
    img[0, 0] = [1e-30, 65504.0, 3.0e38]
    path = tmp_path / "x.exr"
    write_image(path, img)
    assert path.read_bytes()[:4] == b"\x76\x2f\x31\x01"
    np.testing.assert_array_equal(read_image(path), img)


def test_exr_half(tmp_path):
    img = np.array([[[0.5, 2.0, 1000.0], [0.1, 3.0, -4.0]]], np.float32)
    write_image(tmp_path / "h.exr", img, bit_depth=16)
    inp = oiio.ImageInput.open(str(tmp_path / "h.exr"))
    assert inp.spec().format == oiio.TypeDesc("half")
    inp.close()
    np.testing.assert_array_equal(read_image(tmp_path / "h.exr"), img.astype(np.float16).astype(np.float32))
    with pytest.raises(ImageFileError, match="half-float range"):
        write_image(tmp_path / "big.exr", img * 100, bit_depth=16)
    assert not (tmp_path / "big.exr").exists()


def test_grey_image_shapes(tmp_path):
    grey = np.linspace(0, 4, 20, dtype=np.float32).reshape(4, 5)
    write_image(tmp_path / "g.exr", grey)
    back = read_image(tmp_path / "g.exr")
    assert back.shape == (4, 5, 3)
    for c in range(3):
        np.testing.assert_array_equal(back[..., c], grey)


def test_jpeg_round_trip(tmp_path):
    img = np.full((16, 16, 3), 0.2, np.float32)
    img[:, :, 1] = 0.6
    write_image(tmp_path / "a.jpg", img)
    assert (tmp_path / "a.jpg").read_bytes()[:2] == b"\xff\xd8"
    back = read_image(tmp_path / "a.jpg")
    np.testing.assert_allclose(linear_to_srgb(back), linear_to_srgb(img), atol=3 / 255)


def test_grey_png_gives_three_equal_channels(tmp_path):
    codes = np.arange(0, 256, 17, dtype=np.uint8).reshape(2, 8, 1)
    _oiio_write(tmp_path / "grey.png", codes, "uint8")
    back = read_image(tmp_path / "grey.png")
    assert back.shape == (2, 8, 3)
    assert np.array_equal(back[..., 0], back[..., 1]) and np.array_equal(back[..., 0], back[..., 2])
    np.testing.assert_allclose(back[..., 0], srgb_to_linear(codes[..., 0] / 255.0), atol=1e-6)


def test_rgba_png_drops_alpha_without_premultiplying(tmp_path):
    px = np.zeros((3, 4, 4), np.uint8)
    px[..., 0], px[..., 1], px[..., 2], px[..., 3] = 200, 100, 50, 64
    _oiio_write(tmp_path / "rgba.png", px, "uint8", unassociated=True)
    back = read_image(tmp_path / "rgba.png")
    assert back.shape == (3, 4, 3)
    np.testing.assert_allclose(back[0, 0], srgb_to_linear(np.array([200, 100, 50]) / 255.0), atol=1e-6)


def test_16bit_tiff_is_srgb_and_float_tiff_linear(tmp_path):
    codes = np.full((2, 2, 3), 32768, np.uint16)
    _oiio_write(tmp_path / "i.tif", codes, "uint16")
    np.testing.assert_allclose(read_image(tmp_path / "i.tif"), srgb_to_linear(32768 / 65535), atol=1e-6)
    lin = np.full((2, 2, 3), 2.5, np.float32)
    _oiio_write(tmp_path / "f.tif", lin, "float")
    np.testing.assert_array_equal(read_image(tmp_path / "f.tif"), lin)


def test_write_into_new_subfolder(tmp_path):
    path = tmp_path / "a" / "b" / "img.png"
    write_image(path, np.zeros((2, 2, 3), np.float32))
    assert path.is_file() and _listing(path.parent) == ["img.png"]
    write_depth(tmp_path / "c" / "d.exr", np.ones((2, 2), np.float32))
    assert (tmp_path / "c" / "d.exr").is_file()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("name", ["out.png", "out.exr", "out.jpg"])
def test_writing_non_finite_fails_and_leaves_nothing(tmp_path, bad, name):
    img = np.zeros((4, 5, 3), np.float32)
    img[2, 3, 1] = bad
    with pytest.raises(ImageFileError) as info:
        write_image(tmp_path / "sub" / name, img)
    msg = str(info.value)
    assert name in msg and "non-finite" in msg and "row 2, column 3, channel G" in msg
    assert isinstance(info.value, DcdiError) and isinstance(info.value, ValueError)
    assert not (tmp_path / "sub").exists() or _listing(tmp_path / "sub") == []


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "keep.png"
    write_image(path, np.zeros((2, 2, 3), np.float32))
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        write_image(path, np.ones((2, 2, 3), np.float32))
    assert path.read_bytes() == before
    assert _listing(tmp_path) == ["keep.png"]


def test_write_rejects_bad_arguments(tmp_path):
    img = np.zeros((2, 2, 3), np.float32)
    with pytest.raises(ImageFileError, match="extension"):
        write_image(tmp_path / "x.bmp", img)
    with pytest.raises(ImageFileError, match="bit_depth"):
        write_image(tmp_path / "x.jpg", img, bit_depth=16)
    with pytest.raises(ImageFileError, match="bit_depth"):
        write_image(tmp_path / "x.png", img, bit_depth=12)
    with pytest.raises(ImageFileError, match="floating-point"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ImageFileError, match=r"\(H, W\) or \(H, W, 3\)"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 4), np.float32))
    assert _listing(tmp_path) == []


def test_writes_are_deterministic(tmp_path):
    img = _gradient(4, 32)
    for ext in ("png", "exr"):
        write_image(tmp_path / f"a.{ext}", img)
        write_image(tmp_path / f"b.{ext}", img)
        assert (tmp_path / f"a.{ext}").read_bytes() == (tmp_path / f"b.{ext}").read_bytes()


# ---------------------------------------------------------------- reading errors

def test_missing_file_names_it(tmp_path):
    missing = tmp_path / "nowhere" / "missing_picture.png"
    for reader in (read_image, read_depth):
        with pytest.raises(ImageFileError, match="missing_picture.png.*not found"):
            reader(missing)
    with pytest.raises(ImageFileError, match="missing.npy"):
        read_depth(tmp_path / "missing.npy")


def test_unreadable_file_names_it(tmp_path):
    bad = tmp_path / "garbage.png"
    bad.write_text("not an image")
    with pytest.raises(ImageFileError, match="garbage.png"):
        read_image(bad)
    with pytest.raises(ImageFileError, match="is a folder"):
        read_image(tmp_path)


def test_image_without_colour_channels(tmp_path):
    write_depth(tmp_path / "z.exr", np.ones((2, 3), np.float32))
    with pytest.raises(ImageFileError, match=r"z.exr.*channels found: Z"):
        read_image(tmp_path / "z.exr")
    _oiio_write(tmp_path / "two.tif", np.zeros((2, 2, 2), np.uint8), "uint8")  # channels R, G
    with pytest.raises(ImageFileError, match=r"two.tif.*channels found: R, G"):
        read_image(tmp_path / "two.tif")


# ---------------------------------------------------------------- depth

def test_depth_round_trip_keeps_inf_nan_and_blender_background(tmp_path):
    d = np.array([[1.5, np.inf, np.nan, 0.0], [-1.0, 1e10, 1e-3, 123.25]], np.float32)
    path = tmp_path / "depth.exr"
    write_depth(path, d)
    inp = oiio.ImageInput.open(str(path))
    assert inp.spec().channelnames == ("Z",) and inp.spec().format == oiio.TypeDesc("float")
    inp.close()
    back = read_depth(path)
    assert back.dtype == np.float32 and back.shape == d.shape
    np.testing.assert_array_equal(back, d)  # NaN positions must match too
    assert _listing(tmp_path) == ["depth.exr"]


def test_depth_npy(tmp_path):
    d = np.array([[1.0, np.inf], [np.nan, 2.0]])
    write_depth(tmp_path / "d.npy", d)
    back = read_depth(tmp_path / "d.npy")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, d.astype(np.float32))
    np.save(tmp_path / "bad.npy", np.zeros((2, 2, 2)))
    with pytest.raises(ImageFileError, match=r"bad.npy.*2-D"):
        read_depth(tmp_path / "bad.npy")


def test_depth_channel_preference_and_choice(tmp_path):
    h, w = 3, 4
    r = np.full((h, w, 1), 9.0, np.float32)
    z = np.full((h, w, 1), 2.0, np.float32)
    _oiio_write(tmp_path / "rz.exr", np.concatenate([r, r, r, z], -1), "float", ("R", "G", "B", "Z"))
    np.testing.assert_array_equal(read_depth(tmp_path / "rz.exr"), z[..., 0])  # Z before R
    np.testing.assert_array_equal(read_depth(tmp_path / "rz.exr", channel="G"), r[..., 0])
    with pytest.raises(ImageFileError, match=r"rz.exr.*no channel 'nope'.*R, G, B, Z"):
        read_depth(tmp_path / "rz.exr", channel="nope")
    # a plain single-channel R file (e.g. a converted depth) falls back to R
    _oiio_write(tmp_path / "r.exr", z, "float", ("R",))
    np.testing.assert_array_equal(read_depth(tmp_path / "r.exr"), z[..., 0])


def test_depth_from_blender_style_layer_names(tmp_path):
    """Single-part multi-layer file: 'ViewLayer.Depth.Z' beside 'ViewLayer.Normal.Z'."""
    h, w = 2, 3
    names = ["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B", "ViewLayer.Combined.A",
             "ViewLayer.Normal.X", "ViewLayer.Normal.Y", "ViewLayer.Normal.Z", "ViewLayer.Depth.Z"]
    values = [0.25, 0.5, 4.0, 1.0, 0.0, 0.0, -1.0, 7.5]
    px = np.stack([np.full((h, w), v, np.float32) for v in values], -1)
    _oiio_write(tmp_path / "bl.exr", px, "float", names)
    np.testing.assert_array_equal(read_depth(tmp_path / "bl.exr"), np.full((h, w), 7.5, np.float32))
    np.testing.assert_array_equal(read_image(tmp_path / "bl.exr"),
                                  np.broadcast_to(np.float32([0.25, 0.5, 4.0]), (h, w, 3)))


def test_no_depth_channel_lists_what_exists(tmp_path):
    _oiio_write(tmp_path / "n.exr", np.zeros((2, 2, 2), np.float32), "float", ("foo", "bar"))
    with pytest.raises(ImageFileError, match=r"n.exr.*no depth channel.*channels found: bar, foo"):
        read_depth(tmp_path / "n.exr")


def test_integer_depth_file_is_refused(tmp_path):
    _oiio_write(tmp_path / "d16.png", np.full((2, 2, 1), 1000, np.uint16), "uint16")
    with pytest.raises(ImageFileError, match=r"d16.png.*floating-point metres"):
        read_depth(tmp_path / "d16.png")


def test_data_window_is_placed_in_display_window(tmp_path):
    # 2x2 data window at (1, 1) inside a 4x3 display window
    d = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)[..., None]
    _oiio_write(tmp_path / "win.exr", d, "float", ("Z",), window=(1, 1, 0, 0, 4, 3))
    back = read_depth(tmp_path / "win.exr")
    assert back.shape == (3, 4)
    np.testing.assert_array_equal(back[1:3, 1:3], d[..., 0])
    assert np.isnan(back[0]).all() and np.isnan(back[:, 0]).all() and np.isnan(back[:, 3]).all()


# ---------------------------------------------------------------- multi-part EXR

def _multipart(tmp_path, name="mp.exr", depth_parts=(("depth", "depth.Z", 5.0),), writer="openexr"):
    """Part 0 'rgba' (R, G, B), then one single-channel part per depth_parts entry."""
    h, w = 4, 6
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rgb = {"R": xx / 2, "G": yy * 3, "B": np.full((h, w), 12.5, np.float32)}
    path = tmp_path / name
    if writer == "openexr":
        OpenEXR = pytest.importorskip("OpenEXR")
        parts = [OpenEXR.Part({}, dict(rgb), "rgba")]  # Part() turns dict values into Channel objects
        for part_name, channel, value in depth_parts:
            parts.append(OpenEXR.Part({}, {channel: np.full((h, w), value, np.float32) + xx}, part_name))
        OpenEXR.File(parts).write(str(path))
    else:  # OpenImageIO: one subimage per part
        specs, pixels = [], []
        spec = oiio.ImageSpec(w, h, 3, oiio.TypeDesc("float"))
        spec.attribute("name", "rgba")
        specs.append(spec)
        pixels.append(np.stack([rgb["R"], rgb["G"], rgb["B"]], -1))
        for part_name, channel, value in depth_parts:
            spec = oiio.ImageSpec(w, h, 1, oiio.TypeDesc("float"))
            spec.channelnames = (channel,)
            spec.attribute("name", part_name)
            specs.append(spec)
            pixels.append((np.full((h, w), value, np.float32) + xx)[..., None])
        out = oiio.ImageOutput.create("openexr")
        assert out.open(str(path), specs), out.geterror()
        for k, (spec, px) in enumerate(zip(specs, pixels)):
            if k:
                assert out.open(str(path), spec, "AppendSubimage"), out.geterror()
            assert out.write_image(np.ascontiguousarray(px)), out.geterror()
        assert out.close(), out.geterror()
    return path, rgb, xx


@pytest.mark.parametrize("writer", ["openexr", "oiio"])
def test_multipart_exr_depth_in_part_one_and_rgb_in_part_zero(tmp_path, writer):
    path, rgb, xx = _multipart(tmp_path, writer=writer)
    inp = oiio.ImageInput.open(str(path))  # the file really has two parts
    assert inp.spec(0, 0).channelnames == ("R", "G", "B")
    assert inp.spec(1, 0).channelnames == ("depth.Z",)
    inp.close()
    depth = read_depth(path)
    assert depth.dtype == np.float32 and depth.shape == (4, 6)
    np.testing.assert_array_equal(depth, 5.0 + xx)
    np.testing.assert_array_equal(read_depth(path, channel="depth.Z"), 5.0 + xx)
    img = read_image(path)
    assert img.shape == (4, 6, 3)
    np.testing.assert_array_equal(img, np.stack([rgb["R"], rgb["G"], rgb["B"]], -1))


@pytest.mark.parametrize("writer", ["openexr", "oiio"])
def test_multipart_part_name_qualifies_channels(tmp_path, writer):
    # one part per pass, several view layers each with a bare channel "Z"
    path, _, xx = _multipart(tmp_path, depth_parts=(("Layer1.Depth", "Z", 1.0), ("Layer2.Depth", "Z", 2.0)),
                             writer=writer)
    with pytest.raises(ImageFileError) as info:
        read_depth(path)
    msg = str(info.value)
    assert "mp.exr" in msg and "Layer1.Depth.Z" in msg and "Layer2.Depth.Z" in msg and "part 2" in msg
    np.testing.assert_array_equal(read_depth(path, channel="Layer2.Depth.Z"), 2.0 + xx)
    np.testing.assert_array_equal(read_depth(path, channel="layer1.depth.z"), 1.0 + xx)


def test_multipart_missing_channel_lists_parts(tmp_path):
    path, _, _ = _multipart(tmp_path, depth_parts=(("normal", "N.X", 0.0),))
    with pytest.raises(ImageFileError) as info:
        read_depth(path, channel="depth.Z")
    msg = str(info.value)
    assert "mp.exr" in msg and "part 0 'rgba': R, G, B" in msg and "part 1 'normal': N.X" in msg
