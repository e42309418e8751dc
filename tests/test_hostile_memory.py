"""No input file of under 10 MB makes a verb use more than 1.5 GB: each
crafted file (small on disk, huge in what it claims) is refused with one
line, exit 2, and the `dcdi` process's peak resident memory measured by the
kernel (``VmHWM``) stays under the bound."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from support.hostile import constant_exr, display_window_exr, huge_npy, huge_png, zip_bomb_exr

ROOT = Path(__file__).resolve().parents[1]
BOUND = 1.5e9           # bytes of peak resident memory
SMALL = 10e6            # bytes on disk


# the `dcdi` command, then its process's own high-water mark of resident memory (VmHWM: this process's
# memory alone, unlike wait4's ru_maxrss, which keeps the forking test process's peak across exec)
_RUN = """
import atexit, os, sys
def peak():
    with open("/proc/self/status") as f:
        kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    with open(os.environ["DCDI_TEST_PEAK"], "w") as f:
        f.write(str(kb * 1024))
atexit.register(peak)
if os.environ.get("DCDI_TEST_NO_OIIO") == "1":       # the wheel's and Blender's reader: numpy (io.rawexr)
    sys.modules["OpenImageIO"] = None
from dcdi_core.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _dcdi(tmp_path, *argv, oiio: bool = True):
    """(exit code, standard error, peak resident bytes) of `dcdi ARGV` in a process of its own
    (``oiio`` False: OpenImageIO blocked, as in Blender or the wheel without it)."""
    peak = tmp_path / "peak.txt"
    env = {**os.environ, "DCDI_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT),
           "DCDI_TEST_PEAK": str(peak), "DCDI_TEST_NO_OIIO": "0" if oiio else "1"}
    p = subprocess.run([sys.executable, "-c", _RUN, *map(str, argv)], cwd=tmp_path, env=env,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=300)
    return p.returncode, p.stderr, int(peak.read_text())


@pytest.fixture
def small(tmp_path):
    """A 32 x 48 image and depth map beside the crafted files."""
    from dcdi_core.io.images import write_depth, write_image
    write_image(tmp_path / "img.exr", np.full((32, 48, 3), 0.5, np.float32))
    write_depth(tmp_path / "depth.exr", np.full((32, 48), 2.0, np.float32))
    return tmp_path


def _refused(tmp_path, crafted: Path, *argv, words=(), oiio=True):
    assert crafted.stat().st_size < SMALL
    code, err, peak = _dcdi(tmp_path, *argv, oiio=oiio)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert peak < BOUND, f"peak {peak / 1e9:.2f} GB: {err}"
    for w in words:
        assert w in err, err
    return err


@pytest.mark.parametrize("oiio", [True, False])
def test_an_exr_whose_chunk_inflates_far_past_its_scanlines(small, oiio):
    bomb = zip_bomb_exr(small / "bomb.exr", 768 << 20)
    _refused(small, bomb, "correct", "--image", bomb, "--lens", "mos-s1", "--method", "deconv", "--one-depth", "2",
             "-o", small / "out.exr", words=("bomb.exr",), oiio=oiio)


@pytest.mark.parametrize("oiio", [True, False])
def test_a_tiny_data_window_in_a_huge_display_window(small, oiio):
    f = display_window_exr(small / "window.exr", 20000)
    _refused(small, f, "bokeh", "--image", f, "--depth", small / "depth.exr", "--lens", "mos-s1", "--focus", "2",
             "-o", small / "out.exr", words=("window.exr",), oiio=oiio)


@pytest.mark.parametrize("oiio", [True, False])
def test_a_huge_depth_map_beside_a_small_image(small, oiio):
    f = constant_exr(small / "big-depth.exr", 20000, 20000)
    _refused(small, f, "bokeh", "--image", small / "img.exr", "--depth", f, "--lens", "mos-s1", "--focus", "2",
             "-o", small / "out.exr", words=("big-depth.exr",), oiio=oiio)


def test_a_png_whose_header_claims_ten_gigapixels(small):
    f = huge_png(small / "huge.png", 100000, 100000)
    _refused(small, f, "correct", "--image", f, "--lens", "mos-s1", "--method", "deconv", "--one-depth", "2",
             "-o", small / "out.exr", words=("huge.png",))


def test_a_npy_depth_whose_header_claims_more_than_it_holds(small):
    f = huge_npy(small / "huge.npy", 30000, 30000)
    _refused(small, f, "bokeh", "--image", small / "img.exr", "--depth", f, "--lens", "mos-s1", "--focus", "2",
             "-o", small / "out.exr", words=("huge.npy",))


def test_a_capture_record_nested_a_million_deep(small):
    from dcdi_core.io.images import write_image
    write_image(small / "cap.png", np.full((32, 48, 3), 0.5, np.float32))
    side = small / "cap.png.dcdi.json"
    side.write_text("[" * 1_000_000 + "]" * 1_000_000)
    _refused(small, side, "correct", "--image", small / "cap.png", "--depth", small / "depth.exr", "--lens",
             "mos-s1", "--method", "deconv", "-o", small / "out.exr", words=("cap.png",))


def test_a_lens_file_with_sixty_thousand_surfaces(small):
    text = (ROOT / "lenses" / "mos-s1.toml").read_text()
    head, first, rest = text.partition("[[surface]]")
    block = first + rest.split("[[surface]]")[1]
    f = small / "many.toml"
    f.write_text(head.replace('id = "mos-s1"', 'id = "many"') + block * 60_000)
    _refused(small, f, "lens", "info", f, words=("many.toml",))
