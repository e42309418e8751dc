"""Bad or extreme inputs, as a new user gives them (issue 11): each is refused
before any work with exit status 2 and one line that names the file or
option and what is allowed, no traceback, and no output, partial file or
PSF cache left behind; implausible inputs are warned about."""
import errno
import io
import os
import time

import numpy as np
import pytest

from conftest import write_rgbd_scene

from dcdi_core.cli import main
from dcdi_core.errors import DcdiError, InputRangeError, MemoryLimitError, OutputError
from dcdi_core.io.images import write_depth, write_image
from dcdi_core.render.synthetic import synthetic_rgbd

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    img, depth = write_rgbd_scene(tmp_path, monkeypatch, 32, 48)
    return tmp_path, img, depth


def _cli(capsys, *argv):
    t = time.perf_counter()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:                  # argparse's own refusals
        code = e.code
    cap = capsys.readouterr()
    return code, cap.out, cap.err, time.perf_counter() - t


def _refused(capsys, *argv, says=(), fast=True):
    code, out, err, dt = _cli(capsys, *argv)
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err, err
    assert [x for x in lines if x.startswith("dcdi: error:")] == lines[-1:], err     # one line, the last
    for s in says:
        assert s in lines[-1], lines[-1]
    if fast:
        assert dt < 1.0, dt                  # refused from the arguments alone, before any work
    return lines[-1]


def _render(d, command, *extra, out="out.exr", depth="depth.exr"):
    what = ["--focus", "1.5"] if command == "bokeh" and "--focus" not in extra and "--keep" not in extra else []
    return [command, "--image", d / "aif.exr", "--depth", d / depth, "--lens", "mos-s1", "-o", d / out,
            *FAST, *what, *extra]


def _nothing_left(d, *names):
    assert not (d / "cache").exists(), "a PSF was built"
    for n in names:
        assert not (d / n).exists()
    assert not [p for p in d.rglob(".*") if ".tmp" in p.name], "a temporary was left"


@pytest.fixture
def read_only(monkeypatch):
    """Make folders read-only for this process, also as root (where chmod is
    no obstacle): os.access and mkstemp refuse them as the OS would."""
    import tempfile
    folders = []
    real_access, real_mkstemp = os.access, tempfile.mkstemp

    def inside(p):
        return any(os.path.abspath(os.fspath(p)).startswith(os.path.abspath(f)) for f in folders)

    def access(p, mode, *a, **k):
        return False if inside(p) and mode & os.W_OK else real_access(p, mode, *a, **k)

    def mkstemp(*a, dir=None, **k):
        if dir is not None and inside(dir):
            raise PermissionError(errno.EACCES, "Permission denied", str(dir))
        return real_mkstemp(*a, dir=dir, **k)
    monkeypatch.setattr(os, "access", access)
    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)

    def make(folder):
        folder.mkdir(parents=True, exist_ok=True)
        os.chmod(folder, 0o555)
        folders.append(folder)
        return folder
    yield make
    for f in folders:
        os.chmod(f, 0o755)


# ------------------------------------------------------------------ one error family
def test_every_error_kind_is_a_dcdi_error_and_keeps_its_builtin():
    from dcdi_core.io.image_file import ImageFileError
    from dcdi_core.optics.errors import LensFileError, OpticsError, UnknownGlassError
    from dcdi_core.psf.spectral import SpectralFileError
    for cls, builtin in ((OpticsError, Exception), (LensFileError, ValueError), (UnknownGlassError, KeyError),
                         (InputRangeError, ValueError), (ImageFileError, ValueError),
                         (SpectralFileError, ValueError), (OutputError, OSError),
                         (MemoryLimitError, MemoryError)):
        assert issubclass(cls, DcdiError) and issubclass(cls, builtin), cls
    assert str(InputRangeError("--seed", None, "an integer")) == "--seed is missing; needed: an integer"


def test_a_memory_error_anywhere_becomes_one_line(capsys, monkeypatch):
    import dcdi_core.optics.analysis as analysis

    def boom(*a, **k):
        raise MemoryError
    monkeypatch.setattr(analysis, "spot_diagram", boom)
    _refused(capsys, "spot", "mos-s1", "--field", "0", "--depth", "2", "--wavelength", "550",
             says=["out of memory", "--rays"])


# ------------------------------------------------------------------ outputs and the cache
def test_read_only_output_folder_is_refused_before_any_work(scene, capsys, read_only):
    d, _, _ = scene
    ro = read_only(d / "ro")
    _refused(capsys, *_render(d, "simulate", out="ro/sim.exr"), says=[str(ro), "-o", "not writable"])
    _refused(capsys, *_render(d, "simulate", "--sharp-out", d / "ro" / "s.exr", out="sim.exr"),
             says=["--sharp-out", "not writable"])
    _refused(capsys, "psf", "mos-s1", "--field", "0", "--depth", "2", "--png", ro / "k.png", *FAST,
             says=["--png", "not writable"])
    _refused(capsys, "psflib", "build", "mos-s1", "-o", ro / "lib.npz", "--no-cache", *FAST,
             says=["-o", "not writable"])
    _nothing_left(d, "sim.exr")
    assert list(ro.iterdir()) == []


def test_an_output_below_a_file_is_refused(scene, capsys):
    d, _, _ = scene
    (d / "afile").write_text("x")
    _refused(capsys, *_render(d, "bokeh", out="afile/out.png"), says=["afile", "is a file, not a folder"])
    _nothing_left(d)


def test_read_only_cache_folder_is_refused_before_any_work(scene, capsys, read_only, monkeypatch):
    d, _, _ = scene
    ro = read_only(d / "rocache")
    monkeypatch.setenv("DCDI_CACHE_DIR", str(ro))
    _refused(capsys, *_render(d, "simulate"), says=["PSF cache", "DCDI_CACHE_DIR", "not writable"])
    _refused(capsys, "psflib", "build", "mos-s1", "-o", d / "lib.npz", *FAST, says=["DCDI_CACHE_DIR"])
    _nothing_left(d, "out.exr", "lib.npz")


def test_an_oserror_while_writing_becomes_an_output_error(tmp_path, read_only):
    from dcdi_core.atomic import atomic_path
    ro = read_only(tmp_path / "ro")
    with pytest.raises(OutputError, match=r"ro/x\.txt: cannot write here: permission denied"):
        with atomic_path(ro / "x.txt") as tmp:
            tmp.write_text("never")
    with pytest.raises(OutputError, match="a file stands where a folder is needed"):
        (tmp_path / "f").write_text("x")
        with atomic_path(tmp_path / "f" / "y.txt"):
            pass


# ------------------------------------------------------------------ memory
@pytest.mark.parametrize("command, extra, says", [
    ("simulate", ["--rays", "100000"], ["--rays 100000", "GiB", "lower --rays"]),
    ("bokeh", ["--wavelengths", "100000000"], ["--wavelengths 100000000", "available"]),
    ("simulate", ["--kernel", "40001"], ["--kernel 40001", "available"]),
])
def test_work_too_large_for_the_memory_is_refused_naming_the_options(scene, capsys, command, extra, says):
    d, _, _ = scene
    argv = _render(d, command)
    for opt, v in zip(extra[::2], extra[1::2]):
        argv[argv.index(opt) + 1] = v
    _refused(capsys, *argv, says=says)
    _nothing_left(d, "out.exr")


def test_psf_and_spot_refuse_too_many_rays(capsys):
    _refused(capsys, "psf", "mos-s1", "--field", "0", "--depth", "2", "--rays", "200000",
             says=["--rays 200000", "lower --rays"])
    _refused(capsys, "spot", "mos-s1", "--field", "0", "--depth", "2", "--wavelength", "550", "--rays", "400000",
             says=["spot --rays 400000", "available"])


def test_the_memory_check_itself():
    from dcdi_core.psf.compute import PSFSettings, check_psf_memory, psf_memory_bytes
    small = psf_memory_bytes(PSFSettings(), 1)
    assert 1e6 < small < 1e9                                    # one default PSF: some MB
    check_psf_memory(PSFSettings(), 1344, library_psfs=1344, available=8 << 30)
    with pytest.raises(MemoryLimitError, match=r"--rays 64 .* x --wavelengths 31 .* x --kernel 41 .* needs "
                                               r"about .* but 1 MiB are available"):
        check_psf_memory(PSFSettings(), 1344, library_psfs=1344, available=1 << 20)


# ------------------------------------------------------------------ wavelengths: each glass's own range
@pytest.mark.parametrize("wl", ["100", "300", "3000"])
def test_every_command_refuses_wavelengths_beyond_the_glass_data(capsys, wl):
    # MOS-S1 is H-K9L (302-2325 nm): the same rule, the same words, in lens info, spot and psf
    msgs = [_refused(capsys, "lens", "info", "mos-s1", "--wavelength", wl),
            _refused(capsys, "spot", "mos-s1", "--field", "0", "--depth", "2", "--wavelength", wl),
            _refused(capsys, "psf", "mos-s1", "--field", "0", "--depth", "2", "--wavelength", wl, *FAST)]
    for m in msgs:
        assert f"--wavelength = {float(wl)}" in m and "302-2325 nm for lens mos-s1" in m and "H-K9L" in m
    assert len({m for m in msgs}) == 1


def test_simulate_refuses_a_wavelength_beyond_the_glass_data_before_any_work(scene, capsys):
    d, _, _ = scene
    _refused(capsys, *_render(d, "simulate", "--wavelength", "250"), says=["302-2325 nm"])
    _nothing_left(d, "out.exr")


def test_the_lens_api_refuses_them_too():
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.optics.paraxial import first_order
    dg = load_lens("double-gauss")
    assert dg.wavelength_range_nm == (350.0, 2325.0)
    with pytest.raises(InputRangeError, match="350-2325 nm for lens double-gauss .*SF1's data are valid for "
                                              "350-2500 nm"):
        first_order(dg, 340.0)
    with pytest.raises(InputRangeError, match="LAF2's data are valid for 334-2325 nm"):
        dg.refractive_indices([500.0, 2400.0])


# ------------------------------------------------------------------ depth maps and images
def test_a_depth_map_in_millimetres_is_warned_about(scene, capsys):
    d, _, depth = scene
    write_depth(d / "mm.exr", depth * 1000.0)
    code, out, err, _ = _cli(capsys, *_render(d, "simulate", depth="mm.exr"))
    assert code == 0 and "Traceback" not in err
    warn = [x for x in err.splitlines() if x.startswith("dcdi: warning:")]
    assert len(warn) == 1 and "mm.exr" in warn[0] and "% of the pixels lie beyond 100 m" in warn[0]
    assert "the likely unit is mm" in warn[0]


def test_a_depth_map_without_a_valid_pixel_is_refused(scene, capsys):
    d, _, depth = scene
    bad = np.full_like(depth, np.nan)
    bad[: depth.shape[0] // 2] = 0.0
    write_depth(d / "bad.exr", bad)
    for command in ("simulate", "bokeh"):
        _refused(capsys, *_render(d, command, depth="bad.exr"), says=["bad.exr", "no valid depth", "> 0 metres"])
    _nothing_left(d, "out.exr")
    # without the depth map (--fixed-depth) there is nothing to refuse
    code, _, err, _ = _cli(capsys, *_render(d, "simulate", "--fixed-depth", "2", depth="bad.exr"))
    assert code == 0 and "warning" not in err


def test_mostly_invalid_depths_and_negative_light_are_warned_about(scene, capsys):
    d, img, depth = scene
    holes = depth.copy()
    holes[:, : 2 * depth.shape[1] // 3] = np.nan
    write_depth(d / "holes.exr", holes)
    neg = img.copy()
    neg[3, 4] = -0.25
    write_image(d / "neg.exr", neg)
    argv = _render(d, "bokeh", depth="holes.exr")
    argv[argv.index("--image") + 1] = d / "neg.exr"
    code, _, err, _ = _cli(capsys, *argv)
    warn = sorted(x for x in err.splitlines() if x.startswith("dcdi: warning:"))
    assert code == 0 and len(warn) == 2, err
    assert "holes.exr" in warn[0] and "67 % of the pixels are invalid" in warn[0]
    assert "neg.exr" in warn[1] and "1 pixel(s)" in warn[1] and "lowest -0.25" in warn[1]


def test_the_engine_refuses_and_warns_alike():
    from dcdi_core.errors import RenderError
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.inputs import InputWarning
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.render.simulate import simulate
    img, depth = synthetic_rgbd(16, 16, seed=0)
    lens = load_lens("mos-s1")
    with pytest.raises(RenderError, match="no valid depth"):
        simulate(img, np.zeros_like(depth), lens)
    with pytest.raises(RenderError, match="no valid depth"):
        bokeh(img, -depth, lens, BokehOptions(focus_m=2.0))
    from dcdi_core.render.inputs import check_rgbd
    with pytest.warns(InputWarning, match="likely unit is mm"):
        check_rgbd(img, depth * 1000.0)


# ------------------------------------------------------------------ messages and help
def test_messages_name_options_not_python_arguments(scene, capsys):
    d, _, _ = scene
    m = _refused(capsys, *_render(d, "simulate", "--noise"), says=["--seed is missing; needed: an integer"])
    assert "None" not in m
    m = _refused(capsys, "psflib", "show", "mos-s1", "--png", d / "g.png", "--show-depths", "0.5", *FAST,
                 says=["--show-depths = 0.5", ">= 0.7 m"])
    assert "clamp_near" not in m
    m = _refused(capsys, "psf", "mos-s1", "--field", "0", "--depth", "2", "--kernel", "40",
                 says=["--kernel = 40", "odd"])
    m = _refused(capsys, "psflib", "build", "mos-s1", "-o", d / "l.npz", "--near", "5", "--far", "1",
                 says=["--near, --far"])
    _nothing_left(d, "g.png", "l.npz")


def test_range_messages_read_as_ranges(tmp_path, capsys):
    from conftest import singlet_dict
    from dcdi_core.optics.errors import LensFileError
    from dcdi_core.optics.lens import Lens
    bad = singlet_dict()
    bad["surface"][1]["thickness_mm"] = -1.0
    with pytest.raises(LensFileError, match=r"allowed: \[0, 1e\+06\]$") as e:
        Lens.from_dict(bad)
    assert "None" not in str(e.value)


def test_psflib_show_options_have_help(capsys):
    with pytest.raises(SystemExit):
        main(["psflib", "show", "--help"])
    out = capsys.readouterr().out
    for opt, says in (("--png", "the picture to write"), ("--show-fields", "normalised image height"),
                      ("--show-depths", "metres")):
        assert says in out.split(opt)[-1].split("\n  -")[0], opt


def test_lens_info_labels_the_stated_field_of_view_as_what_it_is(capsys):
    code, out, _, _ = _cli(capsys, "lens", "info", "mos-s1")
    diag = [x for x in out.splitlines() if "field of view (diagonal, real)" in x][0]
    assert code == 0 and "stated" not in diag and "42.6" not in diag
    stated = [x for x in out.splitlines() if x.strip().startswith("stated field of view")][0]
    assert "42.6 deg" in stated and "vertical" in stated


# ------------------------------------------------------------------ progress
class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_draws_on_a_terminal_and_is_silent_elsewhere():
    from dcdi_core import progress
    tty, log = _Terminal(), io.StringIO()
    bar = progress.psf_progress("PSFs", stream=tty)
    for done in (4, 8, 12):
        bar(done, 12)
    bar(3, 6)                                              # a second pass starts a new bar
    bar(6, 6)
    text = tty.getvalue()
    assert "PSFs" in text and "12/12" in text and "6/6" in text
    assert progress.psf_progress("PSFs", stream=log) is None and log.getvalue() == ""


def test_the_engine_imports_and_runs_without_tqdm(tmp_path):
    import subprocess
    import sys
    code = """
import sys
sys.modules["tqdm"] = None
from dcdi_core import progress
from dcdi_core.cli import main
assert progress.psf_progress("x") is None and not progress.enabled()
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                       env=dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__))))
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------ no global switches
def test_trace_chunk_is_a_parameter():
    from dcdi_core.optics import trace as T
    from dcdi_core.optics.aiming import pupil_rays, sources, stop_grid
    from dcdi_core.optics.lens import load_lens
    lens = load_lens("mos-s1")
    o, dd, st, _ = pupil_rays(lens, sources(lens, [2.0], field=[0.5]), stop_grid(lens, 40))
    a = T.trace(lens, o, dd, 550.0, status=st)
    b = T.trace(lens, o, dd, 550.0, status=st, chunk=97)
    c = T.trace(lens, o, dd, 550.0, status=st, chunk=10 ** 9)
    assert np.array_equal(a.position_mm, b.position_mm) and np.array_equal(a.position_mm, c.position_mm)
    from dcdi_core import parallel
    assert not hasattr(T, "CHUNK") and T.thread_pool is parallel.thread_pool     # the shared pool
    with pytest.raises(ValueError, match="chunk"):
        T.trace(lens, o, dd, 550.0, chunk=0)


@pytest.mark.parametrize("command, extra, says", [
    ("bokeh", ["--side-by-side", "side.jpg"], ["--side-by-side", "ending in .png"]),
    ("simulate", ["--noise", "--seed", "1", "--full-well", "-1"], ["--full-well = -1.0", "> 0"]),
    ("simulate", ["--noise", "--seed", "1", "--read-noise", "-1"], ["--read-noise = -1.0", ">= 0"]),
    # beyond any sensor: refused before any work, naming the option
    ("simulate", ["--noise", "--seed", "1", "--full-well", "1e30"], ["--full-well = 1e+30", "(0, 1e+09]"]),
    ("simulate", ["--noise", "--seed", "1", "--read-noise", "1e30"], ["--read-noise = 1e+30", "at most the full well"]),
    ("simulate", ["--perturb", "3", "--perturb-fraction", "5"], ["--perturb-fraction = 5.0", "[0, 0.5]"]),
    ("simulate", ["--fixed-depth", "0.1"], ["--fixed-depth = 0.1", ">= 0.7 m"]),
    ("bokeh", ["--keep", "5", "1"], ["--keep = ", "near <= far"]),
])
def test_render_options_found_by_trying_are_refused_before_any_work(scene, capsys, command, extra, says):
    d, _, _ = scene
    _refused(capsys, *_render(d, command, *extra), says=says)
    _nothing_left(d, "out.exr", "side.jpg")


def test_other_outputs_need_their_own_extension(tmp_path, capsys):
    _refused(capsys, "psflib", "build", "mos-s1", "-o", tmp_path / "lib.txt", "--no-cache", *FAST,
             says=["-o", "ending in .npz"])
    _refused(capsys, "psf", "mos-s1", "--field", "0", "--depth", "2", "--png", tmp_path / "k.jpg", *FAST,
             says=["--png", "ending in .png"])
    assert list(tmp_path.iterdir()) == []
