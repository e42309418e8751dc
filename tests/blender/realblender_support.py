"""Shared by the real-Blender suite (`python build.py test-blender`): the add-on and the
factory in a Blender binary as users run it, the UI under Xvfb with
software OpenGL. The scripts that run inside Blender live in
tests/blender/inside/; each writes OUT/result.json.

The Blender is $BLENDER (build.py sets it to the one it found or
provisioned), else `blender` on PATH; without either these tests skip
(build.py test-blender never runs without one)."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
INSIDE = Path(__file__).resolve().parent / "inside"
SCREEN = (1600, 1000)
# frames in Blender's own scripts (bundled add-ons, its modules, its start-up scripts)
BLENDERS_OWN = re.compile(r'File "[^"]*/scripts/(addons_core|modules|startup)/')
FRAME = re.compile(r'^\s*File "')


def tracebacks(log: str) -> list[str]:
    """The Python tracebacks in ``log``: each from its "Traceback" line to
    the exception line that ends it."""
    out, lines = [], log.splitlines()
    for i, line in enumerate(lines):
        if line.lstrip().startswith("Traceback (most recent call last):"):
            j = i + 1
            while j < len(lines) and lines[j][:1].isspace():
                j += 1
            out.append("\n".join(lines[i:j + 1]))
    return out


def our_tracebacks(log: str) -> list[str]:
    """The tracebacks in ``log`` with a frame outside Blender's own scripts:
    ours (the add-on, the factory, the engine, a --python-expr). A
    distribution's Blender can print its own at start-up (Debian's 5.2.2:
    the bundled bl_pkg add-on fails to register without ``cattrs``); those
    are not ours to fail on."""
    return [t for t in tracebacks(log)
            if any(FRAME.match(x) and not BLENDERS_OWN.search(x) for x in t.splitlines())]


def blender_binary() -> str | None:
    return os.environ.get("BLENDER") or shutil.which("blender")


@pytest.fixture(scope="session")
def blender() -> str:
    b = blender_binary()
    if b is None:
        pytest.skip("no Blender binary ($BLENDER or blender on PATH): `python build.py test-blender` finds or "
                    "provisions one")
    return b


@pytest.fixture(scope="session")
def addon_zip(tmp_path_factory) -> Path:
    """The extension zip, built once for the session (what a user installs);
    $DCDI_TEST_ADDON_ZIP names another (an older build, to show a test failing on it)."""
    if os.environ.get("DCDI_TEST_ADDON_ZIP"):
        return Path(os.environ["DCDI_TEST_ADDON_ZIP"])
    sys.path.insert(0, str(ROOT))
    import build
    return build.build_addon(tmp_path_factory.mktemp("dist"))


def user_folders(work: Path) -> dict:
    """Environment of a Blender with user folders of its own in ``work``
    (the add-on installs there, as for a new user) and a PSF cache of its own."""
    return {"BLENDER_USER_RESOURCES": str(work / "user"), "BLENDER_USER_CONFIG": str(work / "user" / "config"),
            "BLENDER_USER_SCRIPTS": str(work / "user" / "scripts"), "DCDI_CACHE_DIR": str(work / "psf-cache")}


def no_splash(blender: str, env: dict) -> None:
    """Save preferences without the splash screen in the user folders of
    ``env`` (a new user's first start shows Quick Setup over the viewport)."""
    code = ("import bpy; p = bpy.context.preferences; p.view.show_splash = False; "
            "p.use_preferences_save = False; bpy.ops.wm.save_userpref()")
    subprocess.run([blender, "-b", "--factory-startup", "--python-expr", code], env=env, cwd=ROOT, check=True,
                   capture_output=True, timeout=300)


def run_inside(blender: str, script: str, work: Path, args: dict, *, ui: bool = False, blend: Path | None = None,
               extra: tuple = (), timeout: int = 600) -> dict:
    """Run tests/blender/inside/<script> in ``blender`` (``ui``: with a window
    under xvfb-run, else --background), handing it ``args`` (JSON, with
    'out': ``work``); returns its result.json, with 'log' (its output's tail)."""
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, **user_folders(work), DCDI_TEST_ARGS=json.dumps({**args, "out": str(work)}))
    env.pop("DCDI_LENS_PATH", None)
    if ui:
        no_splash(blender, env)
    cmd = [blender, *(["-b"] if not ui else []), *([str(blend)] if blend else []), "--python-exit-code", "1",
           *extra, "--python", str(INSIDE / script)]
    if ui:
        cmd = ["xvfb-run", "-a", "-s", f"-screen 0 {SCREEN[0]}x{SCREEN[1]}x24", *cmd]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout, cwd=ROOT)
    log = (p.stdout + p.stderr)[-6000:]
    result = work / "result.json"
    assert p.returncode == 0 and result.exists(), f"exit {p.returncode}\n{log}"
    ours = our_tracebacks(p.stdout + p.stderr)
    assert not ours, "\n\n".join(ours)
    res = json.loads(result.read_text())
    res["log"] = log
    return res
