"""The factory on a Blender without OpenImageDenoise or without OpenImageIO
(as Debian's is): frames rendered undenoised with one warning and recorded
so, a denoised folder never resumed undenoised (nor the reverse), and the
folder written and read through dcdi's own EXR code. The pip bpy module has
the denoiser: its absence is simulated (denoiser_available), and
OpenImageIO is blocked as a Python without it (sys.modules)."""
import json
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blender_addon.factory import batch as factory  # noqa: E402
from blender_addon.factory import options, render  # noqa: E402
from blender_addon.factory.blender import NO_DENOISER, check_cycles, denoiser_available  # noqa: E402
from blender_addon.factory.settings import settings_differences  # noqa: E402
from blender_addon.factory import merge_shards  # noqa: E402
from dcdi_core.io.images import read_depth, read_image, write_image  # noqa: E402

SMALL = ["--resolution", "24", "32", "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]


@pytest.fixture(autouse=True)
def cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "psf-cache"))


def _denoiser(monkeypatch, present: bool):
    """This Blender with or without a denoiser, where the run asks: its options and its render."""
    for module in (options, render):
        monkeypatch.setattr(module, "denoiser_available", lambda scene=None: present)


@pytest.fixture
def no_denoiser(monkeypatch):
    _denoiser(monkeypatch, False)


def _run(out, *extra, recipe="tabletop", count=1):
    return factory.run(["--recipe", recipe, "--count", str(count), "--lens", "mos-s1", "--out", str(out),
                        "--seed", "5", *SMALL, *extra])


def _render_record(out):
    settings = json.loads((out / "dataset.json").read_text())["render"]
    records = [json.loads(x)["render"] for x in (out / "manifest.jsonl").read_text().splitlines()]
    return settings, records


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in root.rglob("*.exr")}


def test_the_denoiser_is_found_where_it_is():
    n = len(bpy.data.scenes)
    assert denoiser_available()                 # the pip bpy module has OpenImageDenoise
    check_cycles()
    assert len(bpy.data.scenes) == n                    # the probes leave no scene behind


def test_without_a_denoiser_frames_are_undenoised_with_one_warning(tmp_path, capsys, no_denoiser):
    assert _run(tmp_path / "a", count=2) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("factory: warning:")]
    assert len(warnings) == 1, err
    assert "no OpenImageDenoise" in warnings[0] and "undenoised (2 samples/pixel)" in warnings[0]
    settings, records = _render_record(tmp_path / "a")
    assert settings["denoise"] is False and settings["no_denoise_reason"] == NO_DENOISER
    assert len(records) == 2 and all(r["denoise"] is False and r["no_denoise_reason"] == NO_DENOISER
                                     for r in records)
    # the very frames --no-denoise renders, without the warning
    assert _run(tmp_path / "b", "--no-denoise", count=2) == 0
    assert "warning" not in capsys.readouterr().err
    assert _files(tmp_path / "a") == _files(tmp_path / "b")
    settings_b, _ = _render_record(tmp_path / "b")
    assert settings_b == dict(settings, no_denoise_reason="--no-denoise")


def test_a_denoised_folder_is_not_resumed_undenoised_nor_the_reverse(tmp_path, capsys, monkeypatch):
    denoised, undenoised = tmp_path / "denoised", tmp_path / "undenoised"
    assert _run(denoised) == 0
    assert "no_denoise_reason" not in _render_record(denoised)[0]
    _denoiser(monkeypatch, False)
    assert _run(undenoised) == 0
    capsys.readouterr()
    before = (denoised / "manifest.jsonl").read_bytes()
    assert _run(denoised, count=2) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("factory: error:") and ("the denoiser (--no-denoise): the folder denoised, this run "
                                                  "undenoised (this Blender has no OpenImageDenoise)") in err, err
    assert (denoised / "manifest.jsonl").read_bytes() == before
    assert _run(undenoised, "--no-denoise", count=2) == 0           # undenoised both: resumed
    _denoiser(monkeypatch, True)
    capsys.readouterr()
    assert _run(undenoised, count=3) == 2
    err = capsys.readouterr().err.strip()
    assert ("the folder undenoised (this Blender has no OpenImageDenoise), this run denoised" in err
            and "\n" not in err), err
    assert _run(undenoised, "--no-denoise", count=3) == 0


def test_setup_render_refuses_a_denoiser_this_blender_lacks(no_denoiser):
    from dcdi_core.errors import RenderError
    from dcdi_core.optics.lens import load_lens
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with pytest.raises(RenderError, match="has no OpenImageDenoise: render undenoised"):
        render.setup_render(bpy.context.scene, load_lens("mos-s1"), 24, 32, render.RenderSettings(), seed=0)
    render.setup_render(bpy.context.scene, load_lens("mos-s1"), 24, 32, render.RenderSettings(denoise=False), 0)
    assert bpy.context.scene.cycles.use_denoising is False


def test_shards_undenoised_for_either_reason_merge_but_not_with_denoised_ones():
    base = {"recipe": "room", "render": {"samples": 8, "denoise": False, "no_denoise_reason": "--no-denoise"}}
    other = {"recipe": "room", "render": {"samples": 8, "denoise": False, "no_denoise_reason": NO_DENOISER}}
    denoised = {"recipe": "room", "render": {"samples": 8, "denoise": True}}
    assert merge_shards.setting_differences(base, other) == []
    assert settings_differences(base, other) == []
    assert merge_shards.setting_differences(base, denoised) == ["the denoiser (--no-denoise): False vs True"]


def test_the_factory_without_openimageio_writes_what_it_writes_with_it(tmp_path, monkeypatch):
    assert _run(tmp_path / "with", count=2) == 0
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "OpenImageIO", None)
        assert _run(tmp_path / "without", count=2) == 0
        assert _run(tmp_path / "again", count=2) == 0
    a, b, c = _files(tmp_path / "with"), _files(tmp_path / "without"), _files(tmp_path / "again")
    assert a.keys() == b.keys() and len(a) == 10
    assert b == c                                        # same bytes on a rerun
    for rel in a:                                        # the same pixels, read by OpenImageIO
        read = read_depth if rel.parts[0] == "depth" else read_image
        np.testing.assert_array_equal(read(tmp_path / "with" / rel), read(tmp_path / "without" / rel))
    assert not list((tmp_path / "without").glob(".*"))  # the hand-over render removed


def test_png_textures_for_the_numpy_recipe_without_openimageio_are_refused_before_the_folder(
        tmp_path, capsys, monkeypatch):
    textures = tmp_path / "textures"
    write_image(textures / "photo.png", np.full((8, 8, 3), 0.4, np.float32))
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)
    out = tmp_path / "ds"
    assert factory.run(["--recipe", "leaves", "--count", "1", "--out", str(out), "--textures", str(textures),
                        *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("factory: error: --textures:") and "photo.png" in err and "OpenImageIO" in err, err
    assert "\n" not in err and not out.exists()
