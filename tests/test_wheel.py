"""The package as a user installs it: `pip wheel .` carries the engine alone
(no add-on, scenes or lab) with every shipped data file (PSF bases, weights,
lenses, the sensor response), and from that wheel,
installed non-editable into a fresh environment and run from a folder outside
the checkout, `dcdi lens info`, `simulate`, `correct`, `bokeh` and `info` work.

The fresh environment is a new venv whose only other package is this
machine's numpy (linked in: no download); scipy, OpenImageIO and torch are
absent there, as in Blender's own Python."""
import json
import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest

from support.build import build_module

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    return build_module().build_wheel(tmp_path_factory.mktemp("wheel"))


def test_wheel_carries_every_shipped_data_file(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    data = [p for p in (ROOT / "dcdi_core").rglob("*") if p.is_file() and p.suffix in (".npz", ".csv")]
    assert len(data) >= 10
    for p in data:
        assert p.relative_to(ROOT).as_posix() in names, p
    for p in (ROOT / "lenses").glob("*.toml"):
        assert f"dcdi_core/lenses/{p.name}" in names, p
    assert not any("__pycache__" in n or n.endswith(".pyc") for n in names)


def test_wheel_holds_the_engine_only(wheel):
    """No add-on, scenes, lab or experiments: `dcdi_core` and its data, every module under 800 lines."""
    z = zipfile.ZipFile(wheel)
    names = z.namelist()
    assert {n.split("/")[0] for n in names} == {"dcdi_core", "dcdi-0.1.0.dist-info"}
    assert not [n for n in names if any(part in ("blender_addon", "scenes", "lab", "experiments")
                                        for part in n.split("/"))]
    long = {n: z.read(n).count(b"\n") for n in names if n.endswith(".py")}
    assert not {n: k for n, k in long.items() if k > 800}
    for data in ("dcdi_core/psf/data/", "dcdi_core/psf/data/basis/", "dcdi_core/psf/data/raymap/",
                 "dcdi_core/psf/data/olf/", "dcdi_core/models/weights/", "dcdi_core/lenses/"):
        assert any(n.startswith(data) and not n.endswith(".py") for n in names), data
    assert "dcdi_core/lenses/mos-s1.toml" in names and "dcdi_core/models/weights/olf-radial.npz" in names
    assert any(n.startswith("dcdi_core/psf/data/") and n.endswith(".csv") for n in names)
    top = z.read("dcdi-0.1.0.dist-info/top_level.txt").decode().split() if \
        "dcdi-0.1.0.dist-info/top_level.txt" in names else ["dcdi_core"]
    assert top == ["dcdi_core"]


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory):
    """(the fresh environment's python, a work folder outside the checkout)."""
    env_dir = tmp_path_factory.mktemp("fresh-env")
    venv.EnvBuilder(with_pip=False, symlinks=True).create(env_dir)
    py = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    import numpy
    # a folder holding this environment's numpy alone: nothing else of it (scipy, torch, ...) leaks in
    only = tmp_path_factory.mktemp("numpy-only")
    for name in ("numpy", "numpy.libs"):
        if (Path(numpy.__file__).parents[1] / name).exists():
            (only / name).symlink_to(Path(numpy.__file__).parents[1] / name)
    (site / "_numpy_only.pth").write_text(f"{only}\n")
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                        "--disable-pip-version-check", "-q", str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    work = tmp_path_factory.mktemp("outside")
    return py, work


def _dcdi(installed, *argv) -> dict | str:
    py, work = installed
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DCDI_LENS_PATH")}
    env.update(DCDI_CACHE_DIR=str(work / "cache"), OMP_NUM_THREADS="1")
    r = subprocess.run([str(py.parent / "dcdi"), *map(str, argv)], capture_output=True, text=True, cwd=work,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    try:
        return json.loads(r.stdout)
    except ValueError:
        return r.stdout


def test_installed_package_is_the_wheels_not_the_checkouts(installed):
    py, work = installed
    r = subprocess.run([str(py), "-c", "import dcdi_core, sys; print(dcdi_core.__file__); "
                        "print(all(m not in sys.modules for m in ('scipy', 'torch')))"],
                       capture_output=True, text=True, cwd=work, check=True)
    where, clean = r.stdout.split()
    assert not where.startswith(str(ROOT)) and "site-packages" in where and clean == "True"


def test_commands_run_from_the_wheel_outside_the_checkout(installed):
    py, work = installed
    info = _dcdi(installed, "lens", "info", "mos-s1", "--json")
    assert info["id"] == "mos-s1" and info["file"].startswith(str(py.parents[1]))
    # a small RGB-D scene written by the installed package itself
    make = ("import numpy as np; from dcdi_core.io.images import write_image, write_depth;"
            "rng = np.random.default_rng(0); img = (0.1 + 0.8 * rng.random((48, 64, 3))).astype(np.float32);"
            "d = np.where(np.arange(64)[None, :] < 32, 0.8, 3.0) * np.ones((48, 1));"
            "write_image('aif.exr', img); write_depth('depth.exr', d.astype(np.float32))")
    subprocess.run([str(py), "-c", make], cwd=work, check=True)
    sim = _dcdi(installed, "simulate", "--image", "aif.exr", "--depth", "depth.exr", "--lens", "mos-s2",
                "--image-pixel-pitch", "0.0122", "--axis", "20", "30", "--psf-source", "basis", "-o", "cap.exr")
    assert sim["psf_source"] == "basis" and sim["basis_file"].startswith(str(py.parents[1]))
    shown = _dcdi(installed, "info", "cap.exr")
    assert "lens_id: mos-s2" in shown and "12.2 um" in shown
    fixed = _dcdi(installed, "correct", "--image", "cap.exr", "--depth", "depth.exr", "--lens", "mos-s2",
                  "--method", "deconv", "-o", "fixed.exr")
    assert fixed["pixel_pitch_mm"] == pytest.approx(0.0122) and fixed["correction"]["method"] == "deconv"
    blur = _dcdi(installed, "bokeh", "--image", "aif.exr", "--depth", "depth.exr", "--lens", "mos-s1",
                 "--keep", "0.7", "0.9", "--psf-source", "basis", "-o", "bokeh.exr")
    assert blur["psf_source"] == "basis"
    check = ("import numpy as np; from dcdi_core.io.images import read_image as r;"
             "print(*[float(np.isfinite(r(f)).all()) for f in ('cap.exr', 'fixed.exr', 'bokeh.exr')])")
    out = subprocess.run([str(py), "-c", check], cwd=work, check=True, capture_output=True, text=True).stdout
    assert out.split() == ["1.0", "1.0", "1.0"]
    assert np.isfinite(sim["not_imaged_pixels"])
