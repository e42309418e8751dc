"""Runs one of the headless add-on scripts (tests/addon/addon_headless*.py)
with the pip bpy module in a fresh interpreter, and returns what it wrote."""
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run_headless(script: str, addon_zip, out: Path, *extra: str) -> dict:
    """``python tests/addon/<script> ZIP OUT [extra...]`` with a PSF cache of
    its own in OUT and no $DCDI_LENS_PATH; its result.json, with 'dir': OUT."""
    env = dict(os.environ, DCDI_CACHE_DIR=str(out / "psf-cache"))
    env.pop("DCDI_LENS_PATH", None)
    p = subprocess.run([sys.executable, str(HERE / script), str(addon_zip), str(out), *extra], capture_output=True,
                       text=True, env=env, timeout=600, cwd=HERE)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    res = json.loads((out / "result.json").read_text())
    res["dir"] = out
    return res
