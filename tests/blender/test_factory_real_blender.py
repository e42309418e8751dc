"""The dataset factory in a real Blender binary, as its docs run it
(``blender --background --python-exit-code 1 --python
blender_addon/factory/batch.py -- ...``), with Blender's OpenImageIO module
and with it blocked (``sys.modules['OpenImageIO'] = None`` before the
factory, as a Blender without the module): exit 0, one warning line where
the build has no OpenImageDenoise and the folder recording its frames as
undenoised, the readers accepting the folder, the same bytes on a rerun.
120 x 160 pixels, one sample a run."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import blender, our_tracebacks  # noqa: E402,F401

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.realblender

BLOCK_OIIO = "import sys; sys.modules['OpenImageIO'] = None"
FACTS = ("import json, sys; sys.path.insert(0, {root!r}); import bpy\n"
         "from blender_addon.factory.blender import denoiser_available\n"
         "try:\n    import OpenImageIO; oiio = True\nexcept ImportError:\n    oiio = False\n"
         "print('FACTS ' + json.dumps({{'version': bpy.app.version_string, 'denoiser': denoiser_available(), "
         "'oiio': oiio}}))")
# what a manifest record holds that differs from run to run: timings, and how many depth bins the
# lens's PSF library held (it counts those the PSF cache on disk already had)
TIMINGS = ("seconds", "cpu_seconds", "stage_seconds")
LENS_RUN_STATE = ("seconds", "depth_bins_computed")


def _env(cache: Path) -> dict:
    return dict(os.environ, DCDI_CACHE_DIR=str(cache))


@pytest.fixture(scope="session")
def facts(blender, tmp_path_factory) -> dict:
    """What this Blender has: its version, OpenImageDenoise, OpenImageIO, and
    how many of its own add-ons fail to register at start-up."""
    p = subprocess.run([blender, "--background", "--factory-startup", "--python-exit-code", "1", "--python-expr",
                        FACTS.format(root=str(ROOT))], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env=_env(tmp_path_factory.mktemp("facts-cache")))
    line = next((x for x in p.stdout.splitlines() if x.startswith("FACTS ")), None)
    assert p.returncode == 0 and line, p.stdout[-3000:] + p.stderr[-3000:]
    return {**json.loads(line[len("FACTS "):]),
            "addon_failures": (p.stdout + p.stderr).count("Exception in module register()")}


@pytest.fixture(scope="session")
def psf_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("psf-cache")


def factory(blender, out: Path, recipe: str, *, oiio: bool, cache: Path, extra=()) -> subprocess.CompletedProcess:
    cmd = [blender, "--background", "--factory-startup", "--python-exit-code", "1",
           *([] if oiio else ["--python-expr", BLOCK_OIIO]),
           "--python", str(ROOT / "blender_addon" / "factory" / "batch.py"), "--",
           "--recipe", recipe, "--count", "1", "--lens", "mos-s1", "--out", str(out), "--seed", "0",
           "--resolution", "120", "160", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300, env=_env(cache))


def fingerprint(folder: Path) -> dict:
    """sha256 of every file but the manifest, and the manifest without its timings."""
    out = {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
           for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "manifest.jsonl"}
    records = [json.loads(x) for x in (folder / "manifest.jsonl").read_text().splitlines()]
    for r in records:
        for k in TIMINGS:
            r.pop(k, None)
        r["render"].pop("seconds", None)
        for lens in r["lenses"].values():
            for k in LENS_RUN_STATE:
                lens.pop(k, None)
    out["manifest.jsonl"] = records
    return out


@pytest.mark.parametrize("oiio", [True, False], ids=["with-openimageio", "openimageio-blocked"])
@pytest.mark.parametrize("recipe", ["room", "tabletop"])
def test_factory_in_a_real_blender(blender, facts, psf_cache, tmp_path, recipe, oiio):
    from dcdi_core.dataset.rgbd import FactoryFolder
    from dcdi_core.io import image_file as images

    a, b = tmp_path / "a", tmp_path / "b"
    p = factory(blender, a, recipe, oiio=oiio, cache=psf_cache)
    log = (p.stdout + p.stderr)[-4000:]
    assert p.returncode == 0, log
    assert not our_tracebacks(p.stdout + p.stderr) and "factory: error" not in log, log
    # the add-ons register once, at start-up: the factory does not re-register them for each sample
    assert (p.stdout + p.stderr).count("Exception in module register()") <= facts["addon_failures"], log
    warnings = [x for x in (p.stdout + p.stderr).splitlines() if x.startswith("factory: warning:")]
    render = json.loads((a / "dataset.json").read_text())["render"]
    (record,) = [json.loads(x) for x in (a / "manifest.jsonl").read_text().splitlines()]
    if facts["denoiser"]:
        assert warnings == [] and render["denoise"] is True and "no_denoise_reason" not in render
    else:                                   # Debian's Blender: undenoised, said once, recorded
        assert len(warnings) == 1 and "no OpenImageDenoise" in warnings[0], warnings
        assert render["denoise"] is False and render["no_denoise_reason"] == "this Blender has no OpenImageDenoise"
        assert record["render"]["denoise"] is False and record["render"]["no_denoise_reason"] == \
            render["no_denoise_reason"]
    assert record["versions"]["blender"] == facts["version"]

    # the readers accept the folder, with OpenImageIO and without it alike
    folder = FactoryFolder(a)
    (sid,) = folder.ids()
    frame, pair = folder.load(sid), folder.pair(sid, "mos-s1")
    assert frame.image.shape == (120, 160, 3) and frame.depth.shape == (120, 160)
    assert np.isfinite(frame.image).all() and np.nanmin(frame.depth) > 0
    assert set(pair) == {"aberrated", "baseline", "sharp"} and all(v.shape == (120, 160, 3) for v in pair.values())
    saved = sys.modules.get("OpenImageIO")
    sys.modules["OpenImageIO"] = None
    try:
        assert not images.have_openimageio()
        again = FactoryFolder(a)
        np.testing.assert_array_equal(again.load(sid).image, frame.image)
        np.testing.assert_array_equal(again.load(sid).depth, frame.depth)
    finally:
        if saved is None:
            sys.modules.pop("OpenImageIO", None)
        else:
            sys.modules["OpenImageIO"] = saved
    r = subprocess.run([sys.executable, "-m", "dcdi_core", "dataset", "stats", str(a), "--out", str(tmp_path / "r"),
                        "--lens", "mos-s1"], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env=_env(psf_cache))
    assert r.returncode == 0 and (tmp_path / "r" / "report.md").exists(), r.stderr[-3000:]

    # a rerun into a fresh folder: the same bytes
    p2 = factory(blender, b, recipe, oiio=oiio, cache=psf_cache)
    assert p2.returncode == 0, (p2.stdout + p2.stderr)[-4000:]
    assert fingerprint(a) == fingerprint(b)


def test_a_denoised_folder_is_not_resumed_undenoised(blender, facts, psf_cache, tmp_path):
    """Resuming in a Blender without OpenImageDenoise a folder whose settings
    say denoised is refused in one line, naming the denoiser."""
    if facts["denoiser"]:
        pytest.skip(f"this Blender ({facts['version']}) has OpenImageDenoise")
    p = factory(blender, tmp_path, "room", oiio=False, cache=psf_cache)
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    settings = json.loads((tmp_path / "dataset.json").read_text())
    settings["render"]["denoise"] = True                  # as a Blender with the denoiser records it
    del settings["render"]["no_denoise_reason"]
    (tmp_path / "dataset.json").write_text(json.dumps(settings, indent=2) + "\n")
    p = factory(blender, tmp_path, "room", oiio=False, cache=psf_cache, extra=("--count", "2"))
    errors = [x for x in p.stderr.splitlines() if x.startswith("factory: error:")]
    assert p.returncode == 2 and len(errors) == 1 and not our_tracebacks(p.stderr), p.stderr[-3000:]
    assert "the denoiser (--no-denoise): the folder denoised, this run undenoised" in errors[0]


BLENDER_STARTUP = """Traceback (most recent call last):
  File "/usr/share/blender/scripts/modules/addon_utils.py", line 544, in enable
    mod.register()
  File "/usr/share/blender/scripts/addons_core/bl_pkg/__init__.py", line 580, in _restore
    from _bpy_internal.http import downloader as http_dl
ModuleNotFoundError: No module named 'cattrs'
"""
OURS = """Traceback (most recent call last):
  File "/usr/share/blender/scripts/modules/addon_utils.py", line 544, in enable
    mod.register()
  File "/home/u/.config/blender/5.2/extensions/user_default/dcdi/__init__.py", line 12, in register
    bpy.utils.register_class(cls)
ValueError: register_class(...): already registered
"""


def test_blenders_own_tracebacks_are_told_from_ours():
    """The log filter the factory tests use: a traceback wholly inside
    Blender's own scripts is not ours; one with a frame of the add-on is, and
    so is one of a --python-expr."""
    expr = 'Traceback (most recent call last):\n  File "<string>", line 1, in <module>\nNameError: x\n'
    assert our_tracebacks("Blender 5.2.2\n" + BLENDER_STARTUP + "factory: room\n") == []
    assert our_tracebacks(BLENDER_STARTUP + OURS) == [OURS.rstrip("\n")]
    assert our_tracebacks(expr) == [expr.rstrip("\n")]


def test_the_factory_command_runs_a_real_blender_from_any_folder(blender, psf_cache, tmp_path):
    """`dcdi-factory --blender BLENDER ...` from a folder outside the clone:
    the factory under that Blender, --background, its folder at the caller's
    relative path."""
    script = Path(sys.executable).with_name("dcdi-factory")
    away = tmp_path / "elsewhere"
    away.mkdir()
    # GIT_DIR: the provisioned Blender's sandbox (real_blender.sh) binds the clone it finds from git; a Blender
    # of one's own needs nothing
    env = dict(_env(psf_cache), GIT_DIR=str(ROOT / ".git"), GIT_WORK_TREE=str(ROOT))
    p = subprocess.run([str(script), "--blender", blender, "--recipe", "room", "--count", "1", "--lens", "mos-s1",
                        "--out", "ds", "--seed", "0", "--resolution", "24", "32", "--cycles-samples", "2",
                        "--psf-rays", "12", "--psf-wavelengths", "3"], cwd=away, env=env, capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    records = [json.loads(x) for x in (away / "ds" / "manifest.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == ["room-000000"] and records[0]["render"]["engine"] == "CYCLES"
