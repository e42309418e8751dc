"""Capture records: what an image file remembers of how it was made.

The record survives both EXR writers (OpenImageIO's and rawexr's) and both
readers, lives in a sidecar for PNG and JPEG (removed when the image is
written again without one), refuses damaged or foreign records naming the
file, and `dcdi info` prints it."""
import json
import sys

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.io import capture_record as cr
from dcdi_core.io import images
from dcdi_core.io.image_file import ImageFileError, have_openimageio
from dcdi_core.io.images import write_image


def record(**kw):
    base = dict(kind="simulated", lens_id="mos-s2", prescription_sha256="ab" * 32, pixel_pitch_mm=0.0122,
                axis_px=(20.0, 30.5), image_size=(8, 12), focus_distance_m=1.5, psf_source="basis",
                noise={"full_well_electrons": 9000.0, "read_noise_electrons": 2.5, "seed": 4},
                distortion_applied=True)
    return cr.CaptureRecord(**{**base, **kw})


IMG = np.linspace(0.0, 1.0, 8 * 12 * 3, dtype=np.float32).reshape(8, 12, 3)


@pytest.mark.parametrize("writer", ["openimageio", "rawexr"])
def test_exr_header_round_trip(tmp_path, monkeypatch, writer):
    if writer == "rawexr":
        monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    elif not have_openimageio():
        pytest.skip("OpenImageIO not installed")
    r = record()
    write_image(tmp_path / "a.exr", IMG, record=r)
    assert cr.read_record(tmp_path / "a.exr") == r
    assert not cr.sidecar_path(tmp_path / "a.exr").exists()
    np.testing.assert_array_equal(images.read_image(tmp_path / "a.exr"), IMG)
    write_image(tmp_path / "a.exr", IMG)
    assert cr.read_record(tmp_path / "a.exr") is None


def test_png_sidecar_written_and_removed(tmp_path):
    if not have_openimageio():
        pytest.skip("PNG needs OpenImageIO")
    r = record(noise=None)
    write_image(tmp_path / "a.png", IMG, record=r)
    side = tmp_path / "a.png.dcdi.json"
    assert side.is_file() and cr.read_record(tmp_path / "a.png") == r
    write_image(tmp_path / "a.png", IMG)            # the image rewritten without a record: no stale one
    assert not side.exists() and cr.read_record(tmp_path / "a.png") is None


@pytest.mark.parametrize("bad, words", [
    ({"pixel_pitch_mm": -1.0}, "pixel_pitch_mm"), ({"pixel_pitch_mm": float("nan")}, "pixel_pitch_mm"),
    ({"axis_px": (1.0,)}, "axis_px"), ({"kind": "photo"}, "kind"), ({"image_size": (0, 4)}, "image_size"),
    ({"noise": {"full_well_electrons": 0, "read_noise_electrons": 1, "seed": 1}}, "full_well"),
    ({"extra": {"x": object()}}, "extra")])
def test_bad_records_are_refused_when_made(bad, words):
    with pytest.raises(ValueError, match=words):
        record(**bad)


@pytest.mark.parametrize("text, words", [("{not json", "not JSON"), ('{"format": 99, "kind": "simulated"}',
                                                                       "format 99"),
                                         ('{"format": 1, "kind": "simulated", "colour": 1}', "unknown field"),
                                         ('{"format": 1, "kind": "simulated", "pixel_pitch_mm": 0}',
                                          "pixel_pitch_mm")])
def test_damaged_sidecar_names_the_file(tmp_path, text, words):
    (tmp_path / "a.png").write_bytes(b"")
    cr.sidecar_path(tmp_path / "a.png").write_text(text)
    with pytest.raises(cr.CaptureRecordError, match=words) as e:
        cr.read_record(tmp_path / "a.png")
    assert "a.png.dcdi.json" in str(e.value)


def test_record_refuses_a_non_record(tmp_path):
    with pytest.raises(ImageFileError, match="CaptureRecord"):
        write_image(tmp_path / "a.exr", IMG, record={"lens_id": "mos-s1"})
    assert not (tmp_path / "a.exr").exists()


def test_dcdi_info_prints_the_record(tmp_path, capsys):
    write_image(tmp_path / "a.exr", IMG, record=record())
    assert main(["info", str(tmp_path / "a.exr")]) == 0
    out = capsys.readouterr().out
    assert "8 x 12 px" in out and "lens_id: mos-s2" in out and "12.2 um" in out and "row 20, col 30.5" in out
    assert main(["info", "--json", str(tmp_path / "a.exr")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["record"]["pixel_pitch_mm"] == 0.0122 and d["record_in"] == "the EXR header"
    write_image(tmp_path / "b.exr", IMG)
    assert main(["info", str(tmp_path / "b.exr")]) == 0
    assert "no capture record" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "missing.exr")]) == 2
    assert "missing.exr" in capsys.readouterr().err


def test_resized_capture_ignores_its_record():
    """A record made for another size describes other pixels: ignored, with a note."""
    from dcdi_core.app.records import recorded_defaults
    from dcdi_core.optics.lens import load_lens
    lens = load_lens("mos-s2")
    render, notes = recorded_defaults(None, lens, record(), (16, 24), "the capture")
    assert render is None and "ignored" in notes[0]
    render, notes = recorded_defaults(None, lens, record(prescription_sha256=cr.prescription_sha256(lens)),
                                      (8, 12), "the capture")
    assert render.image_pixel_pitch_mm == 0.0122 and render.axis_px == (20.0, 30.5) and notes == []
    assert render.psf.focus_distance_m == 1.5
    _, notes = recorded_defaults(None, lens, record(), (8, 12), "the capture")
    assert "prescription" in notes[0]
