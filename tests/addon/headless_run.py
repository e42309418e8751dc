"""Runs one of the headless add-on scripts (tests/addon/addon_headless*.py)
with the pip bpy module in a fresh interpreter, and returns what it wrote."""
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run_headless(script: str, addon_zip, out: Path, *extra: str, blender: str | None = None) -> dict:
    """``python tests/addon/<script> ZIP OUT [extra...]`` (the pip bpy
    module), or with ``blender`` the same script in that Blender binary in
    the background, with a PSF cache of its own in OUT and no
    $DCDI_LENS_PATH; its result.json, with 'dir': OUT."""
    env = dict(os.environ, DCDI_CACHE_DIR=str(out / "psf-cache"), BLENDER_USER_RESOURCES=str(out / "blender-user"))
    env.pop("DCDI_LENS_PATH", None)
    args = [str(addon_zip), str(out), *extra]
    if blender is None:
        cmd = [sys.executable, str(HERE / script), *args]
    else:       # this folder on its sys.path first: the script imports its neighbours
        cmd = [blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr",
               f"import sys; sys.path.insert(0, {str(HERE)!r})", "--python", str(HERE / script), "--", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900, cwd=HERE)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    res = json.loads((out / "result.json").read_text())
    res["dir"] = out
    return res
