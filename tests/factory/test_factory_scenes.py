"""The factory's scenes: the user's textures, the exposure, the numpy recipe, clutter."""
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.io.images import read_depth, read_image, write_image

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--resolution", "24", "32", "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]


@pytest.fixture(autouse=True)
def cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "psf-cache"))


def _factory():
    pytest.importorskip("bpy")
    from blender_addon.factory import batch
    return batch


def _records(out):
    return [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]


def _two_textures(folder: Path) -> Path:
    rng = np.random.default_rng(0)
    folder.mkdir()
    write_image(folder / "bricks_diff_1k.png", rng.uniform(0.1, 0.6, (16, 16, 3)).astype(np.float32))
    write_image(folder / "bricks_nor_gl_1k.png", np.full((16, 16, 3), 0.5, np.float32))
    write_image(folder / "photo.jpg", rng.uniform(0.1, 0.6, (12, 20, 3)).astype(np.float32))
    return folder


def test_a_texture_folder_of_two_images_is_used_and_recorded(tmp_path):
    batch = _factory()
    tex = _two_textures(tmp_path / "tex")
    out = tmp_path / "ds"
    assert batch.run(["--recipe", "tabletop", "--count", "1", "--out", str(out), "--textures", str(tex),
                      *SMALL]) == 0
    scene = _records(out)[0]["scene"]
    assert scene["texture_sets"] == ["bricks_1k", "photo"]
    assert scene["materials"].get("image", 0) >= 2 and sum(scene["materials"].values()) > 10
    assert 20 <= scene["objects"] <= 60
    assert str(tex) in json.loads((out / "dataset.json").read_text())["scene"]["textures"]


@pytest.mark.parametrize("make, says", [
    (lambda d: d.mkdir(), ["--textures", "no image files"]),
    (lambda d: (d.mkdir(), (d / "notes.txt").write_text("x")), ["--textures", "no image files"]),
    (lambda d: (d.mkdir(), (d / "broken.png").write_bytes(b"not a png")), ["broken.png", "cannot be read"]),
    (lambda d: None, ["--textures", "not found"]),
])
def test_an_empty_or_unreadable_texture_folder_is_refused_before_any_render(tmp_path, capsys, make, says):
    batch = _factory()
    tex = tmp_path / "tex"
    make(tex)
    out = tmp_path / "ds"
    t = time.perf_counter()
    assert batch.run(["--recipe", "room", "--count", "1", "--out", str(out), "--textures", str(tex), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("factory: error:") and "\n" not in err, err
    assert all(s in err for s in says), err
    assert not out.exists() and time.perf_counter() - t < 2.0


def test_resuming_with_another_texture_folder_or_exposure_is_refused(tmp_path, capsys):
    batch = _factory()
    tex = _two_textures(tmp_path / "tex")
    out = tmp_path / "ds"
    base = ["--recipe", "plane", "--count", "2", "--out", str(out), *SMALL]
    assert batch.run([*base, "--textures", str(tex)]) == 0
    capsys.readouterr()
    assert batch.run(base) == 2
    assert "--textures: the folder" in capsys.readouterr().err
    assert batch.run([*base, "--textures", str(tex), "--exposure", "off"]) == 2
    assert "--exposure: the folder auto" in capsys.readouterr().err


def test_a_folder_made_before_the_scenes_changed_is_not_resumed():
    from blender_addon.factory.settings import RECIPES_VERSION, settings_differences
    have = {"recipe": "room", "seed": 0}
    want = {"recipe": "room", "seed": 0, "scene": {"recipes_version": RECIPES_VERSION}}
    assert settings_differences(have, want) == [
        "the scene recipes: the folder was made by an older factory, before its scenes changed"]


def test_exposure_keeps_clipping_under_its_bound_and_off_keeps_the_render(tmp_path):
    batch = _factory()
    a, b = tmp_path / "a", tmp_path / "b"
    assert batch.run(["--recipe", "room", "--count", "1", "--out", str(a), *SMALL]) == 0
    assert batch.run(["--recipe", "room", "--count", "1", "--out", str(b), "--exposure", "off", *SMALL]) == 0
    ea, eb = _records(a)[0]["scene"]["exposure"], _records(b)[0]["scene"]["exposure"]
    img_a, img_b = read_image(a / "aif" / "room-000000.exr"), read_image(b / "aif" / "room-000000.exr")
    assert eb["gain"] == 1.0 and ea["gain"] != 1.0
    np.testing.assert_allclose(img_a, img_b * np.float32(ea["gain"]), rtol=1e-5, atol=1e-7)
    assert (img_a.max(axis=-1) > 1.0).mean() <= 0.003 + 1e-9 and ea["clipped"] <= 0.003


def _leaves_without_blender(out: Path, *extra: str) -> subprocess.CompletedProcess:
    code = ("import sys; sys.modules['bpy'] = None\n"          # importing bpy raises: the recipe must not need it
            "from blender_addon.factory.batch import run\n"
            f"sys.exit(run({['--recipe', 'leaves', '--count', '2', '--out', str(out), *SMALL, *extra]!r}))")
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_the_numpy_recipe_runs_without_blender_and_writes_the_same_folder(tmp_path):
    p = _leaves_without_blender(tmp_path / "a")
    assert p.returncode == 0, p.stderr
    recs = _records(tmp_path / "a")
    assert [r["id"] for r in recs] == ["leaves-000000", "leaves-000001"]
    assert recs[0]["render"]["engine"] == "numpy" and recs[0]["versions"]["blender"] is None
    for r in recs:
        img = read_image(tmp_path / "a" / "aif" / f"{r['id']}.exr")
        depth = read_depth(tmp_path / "a" / "depth" / f"{r['id']}.exr")
        assert img.shape == (24, 32, 3) and np.isfinite(img).all()
        assert ((depth >= 0.7) & np.isfinite(depth)).all()
        for kind in ("aberrated", "baseline", "sharp"):
            assert (tmp_path / "a" / "mos-s1" / kind / f"{r['id']}.exr").exists()
    p = _leaves_without_blender(tmp_path / "b")
    assert p.returncode == 0, p.stderr
    files = sorted(x.relative_to(tmp_path / "a") for x in (tmp_path / "a").rglob("*.exr"))
    assert files and all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)


def test_a_blender_recipe_without_blender_is_refused_by_name(tmp_path):
    code = ("import sys; sys.modules['bpy'] = None\n"
            "from blender_addon.factory.batch import run\n"
            f"sys.exit(run(['--recipe', 'room', '--count', '1', '--out', {str(tmp_path / 'x')!r}]))")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode != 0 and "no bpy module" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "x").exists()
