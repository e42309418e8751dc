"""Hostile numbers and failing surroundings: a clipping warning that travels
with the PSFs it describes, pixel pitches no kernel can hold or no integer
can count, a PSF cache that cannot be written, and pictures asked for
without matplotlib. Each is refused (or survived) in one line before any
work; each test here fails on the code before its fix (but the damaged
cache's, which documents behaviour that was already right)."""
import errno
import math
import sys
import warnings

import numpy as np
import pytest

from support.build import ROOT
from support.cli import run_cli

from dcdi_core.errors import InputRangeError
from dcdi_core.io.capture_record import CaptureRecord
from dcdi_core.io.images import write_depth, write_image
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
from dcdi_core.psf.library import CacheWarning, LibraryGrid, PSFLibrary
from dcdi_core.render.request import RenderRequest
from dcdi_core.psf.library import MAX_FITTED_KERNEL
from dcdi_core.render.synthetic import synthetic_rgbd

# a library small enough to trace in a fraction of a second, whose 5 px kernels clip mos-s1's defocus
TINY = PSFSettings(kernel_size=5, pupil_samples=8, n_wavelengths=3, pixel_pitch_mm=0.0122)
GRID = LibraryGrid(n_fields=2, n_depths=2)
QUICK = ["--rays", "8", "--wavelengths", "3"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    """A 24 x 32 RGB-D scene (aif.exr, depth.exr) and a PSF cache of the test's own (not yet made)."""
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    img, depth = synthetic_rgbd(24, 32, seed=1)
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    return tmp_path


def _clip_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "clips up to" in line]


def _one_line_refusal(code, err, *says):
    assert code == 2 and "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("dcdi: error:")]
    assert len(lines) == 1, err
    for s in says:
        assert s in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ 1. the clipping warning travels
def test_clipped_library_warns_again_when_served_from_the_cache(tmp_path):
    with pytest.warns(KernelTooSmallWarning, match="clips up to") as first:
        traced = PSFLibrary.open(load_lens("mos-s1"), TINY, GRID, cache_dir=tmp_path)
        assert traced.ensure(bins=[0, 1]) == [0, 1]
    with pytest.warns(KernelTooSmallWarning, match="clips up to") as again:
        cached = PSFLibrary.open(load_lens("mos-s1"), TINY, GRID, cache_dir=tmp_path)
        assert cached.ensure(bins=[0, 1]) == []                 # nothing traced: all from the cache file
    told = [str(w.message) for w in first if issubclass(w.category, KernelTooSmallWarning)]
    assert [str(w.message) for w in again if issubclass(w.category, KernelTooSmallWarning)] == told
    assert len(told) == 1
    # the figures are the file's arrays, per bin: the same numbers as traced
    np.testing.assert_array_equal(cached.energy_outside, traced.energy_outside)
    np.testing.assert_array_equal(cached.kernel_size_needed, traced.kernel_size_needed)


def test_clip_warning_speaks_of_the_bins_served_only(tmp_path):
    lens = load_lens("mos-s1")
    PSFLibrary.open(lens, TINY, GRID, cache_dir=tmp_path).ensure(bins=[0, 1, 2])
    cached = PSFLibrary.open(lens, TINY, GRID, cache_dir=tmp_path)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        cached.ensure(bins=[2])
    worst = cached.energy_outside[2].max()
    told = [str(w.message) for w in got if issubclass(w.category, KernelTooSmallWarning)]
    assert told == ([f"PSF library of mos-s1: the 5 x 5 kernel clips up to {worst:.1%} of a channel's energy; "
                     f"a kernel of {cached.kernel_size_needed[2].max()} x {cached.kernel_size_needed[2].max()} "
                     "holds 99 % of the rays"] if worst > 0.01 else [])


def test_a_library_file_shows_its_clipped_kernels_too(tmp_path, capsys):
    lib = PSFLibrary.open(load_lens("mos-s1"), TINY, GRID, cache=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        lib.build()
    lib.save(tmp_path / "lib.npz")
    code, _, err = run_cli(capsys, "psflib", "show", tmp_path / "lib.npz", "--png", tmp_path / "grid.png")
    assert code == 0 and len(_clip_lines(err)) == 1, err


def test_every_job_warns_once_whether_it_traces_or_reads_the_cache(scene, capsys):
    argv = ["simulate", "--image", scene / "aif.exr", "--depth", scene / "depth.exr", "--lens", "mos-s1",
            "--psf-source", "trace", "--image-pixel-pitch", "0.0122", "--kernel", "5", *QUICK]
    code, _, traced = run_cli(capsys, *argv, "-o", scene / "a.exr")
    assert code == 0 and len(_clip_lines(traced)) == 1, traced
    code, _, cached = run_cli(capsys, *argv, "-o", scene / "b.exr")
    assert code == 0 and _clip_lines(cached) == _clip_lines(traced), cached


# ------------------------------------------------------------------ 2. a pitch no kernel can hold
def test_the_smallest_pitch_is_the_diffraction_limit_over_the_largest_kernel():
    from dcdi_core.psf.compute import AIRY_DIAMETER, pixel_pitch_range_mm
    lens = load_lens("mos-s2")
    lo, hi = pixel_pitch_range_mm(lens, PSFSettings(), MAX_FITTED_KERNEL)
    from dcdi_core.optics.analysis import working_f_number
    assert lo == pytest.approx(AIRY_DIAMETER * 400e-6 * working_f_number(lens, 400.0) / MAX_FITTED_KERNEL)
    assert hi == pytest.approx(2 * lens.sensor.semi_diagonal_mm)
    with pytest.raises(InputRangeError, match="image_pixel_pitch_mm") as e:
        RenderRequest(lens, image_pixel_pitch_mm=lo * 0.99)
    assert f"{lo:.3g} to" in str(e.value)
    RenderRequest(lens, image_pixel_pitch_mm=lo * 1.01)              # just inside: allowed
    # without fitting, the kernel given is the largest: a larger floor
    with pytest.raises(InputRangeError, match="at most 15 px"):
        RenderRequest(lens, psf=PSFSettings(kernel_size=15), fit_kernel=False, image_pixel_pitch_mm=lo * 1.01)


@pytest.mark.parametrize("lens_id", ["mos-s1", "mos-s2", "double-gauss", "6p"])
def test_every_paper_lens_own_pitch_is_allowed(lens_id):
    from dcdi_core.psf.compute import check_pixel_pitch
    lens = load_lens(lens_id)
    pitch = 2 * lens.sensor.semi_diagonal_mm / math.hypot(*lens.sensor.resolution_px)
    assert check_pixel_pitch(lens, PSFSettings(), pitch) == pitch


@pytest.mark.parametrize("option", ["--image-pixel-pitch", "--pixel-pitch"])
def test_bokeh_at_a_pitch_no_kernel_holds_is_refused_before_tracing(scene, capsys, option):
    code, out, err = run_cli(capsys, "bokeh", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                             "--lens", "mos-s2", "--focus", "2", "-o", scene / "o.exr", option, "1e-9",
                             "--psf-source", "trace", *QUICK)
    line = _one_line_refusal(code, err, "--pixel-pitch", "1e-09", "mm", "129 px")   # the option's one name
    assert "2.47e-05 to" in line                          # the smallest pitch allowed, in mm
    assert not (scene / "cache").exists() and not (scene / "o.exr").exists()


def test_psf_at_a_pitch_no_kernel_holds_is_refused_before_tracing(scene, capsys):
    code, _, err = run_cli(capsys, "psf", "mos-s2", "--depth", "1", "--field", "0", "--pixel-pitch", "1e-9",
                           "--psf-source", "trace", *QUICK)
    _one_line_refusal(code, err, "--pixel-pitch", "41 px")
    code, _, err = run_cli(capsys, "psflib", "build", "mos-s2", "-o", scene / "l.npz", "--pixel-pitch", "1e-9",
                           *QUICK)
    _one_line_refusal(code, err, "--pixel-pitch")
    assert not (scene / "cache").exists()


def test_the_pitch_an_image_size_gives_is_checked_too():
    with pytest.raises(InputRangeError, match="from its size"):
        RenderRequest(load_lens("double-gauss")).plan(100_000, 100_000)


# ------------------------------------------------------------------ 3. pitches no integer can count
def test_correct_at_an_absurd_pitch_is_one_line(scene, capsys):
    for pitch in ("1e-300", "1e300"):
        code, _, err = run_cli(capsys, "correct", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                               "--lens", "mos-s2", "--method", "deconv", "--image-pixel-pitch", pitch,
                               "-o", scene / "out.exr")
        _one_line_refusal(code, err, "--pixel-pitch", "28.15 mm")
    assert not (scene / "out.exr").exists() and not (scene / "cache").exists()


def test_a_recorded_absurd_pitch_is_one_line(scene, capsys):
    img, _ = synthetic_rgbd(24, 32, seed=1)
    write_image(scene / "cap.exr", img, record=CaptureRecord(kind="simulated", lens_id="mos-s2",
                                                             pixel_pitch_mm=1e-300))
    code, _, err = run_cli(capsys, "correct", "--image", scene / "cap.exr", "--depth", scene / "depth.exr",
                           "--lens", "mos-s2", "--method", "deconv", "-o", scene / "out.exr")
    _one_line_refusal(code, err, "pixel_pitch_mm", "1e-300")
    assert not (scene / "out.exr").exists()


def test_the_engine_refuses_an_absurd_pitch_before_tracing():
    lens = load_lens("mos-s2")
    for pitch in (1e-300, 1e300):
        with pytest.raises(InputRangeError, match="pixel_pitch_mm"):
            psf(lens, depth_m=1.0, field=0.0, settings=PSFSettings(pupil_samples=8, n_wavelengths=3,
                                                                    pixel_pitch_mm=pitch))
    for pitch in (math.inf, math.nan, -1.0):
        with pytest.raises(InputRangeError, match="pixel_pitch_mm"):
            PSFSettings(pixel_pitch_mm=pitch)


# ------------------------------------------------------------------ 4. a PSF cache that cannot be written
def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("where", ["save", "write"])
def test_a_full_cache_keeps_the_psfs_in_memory_with_one_warning(tmp_path, monkeypatch, where):
    if where == "save":                         # the library's write fails as a whole
        monkeypatch.setattr(PSFLibrary, "save", _no_space)
    else:                                       # the bytes fail inside atomic_path: an OutputError
        from dcdi_core.io import npzfile
        monkeypatch.setattr(npzfile, "save_npz", _no_space)
    lib = PSFLibrary.open(load_lens("mos-s1"), TINY, GRID, cache_dir=tmp_path / "cache")
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        assert lib.ensure(bins=[0]) == [0]
        assert lib.ensure(bins=[1]) == [1]              # not tried again, not warned again
    said = [str(w.message) for w in got if issubclass(w.category, CacheWarning)]
    assert len(said) == 1 and "could not be written" in said[0] and "no space left" in said[0], said
    assert lib.computed[[0, 1]].all() and lib.psf[[0, 1]].sum() > 0
    assert not list((tmp_path / "cache").glob("*.npz"))


def test_a_job_with_a_full_cache_finishes_saying_so_once(scene, capsys, monkeypatch):
    monkeypatch.setattr(PSFLibrary, "save", _no_space)
    code, _, err = run_cli(capsys, "bokeh", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                           "--lens", "mos-s2", "--focus", "2", "-o", scene / "o.exr", "--psf-source", "trace",
                           "--image-pixel-pitch", "0.0122", "--kernel", "15", *QUICK)
    assert code == 0 and (scene / "o.exr").exists(), err
    assert sum("could not be written" in line for line in err.splitlines()) == 1, err


def test_a_damaged_cache_file_is_traced_again(tmp_path):
    lens = load_lens("mos-s1")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        first = PSFLibrary.open(lens, TINY, GRID, cache_dir=tmp_path)
        first.ensure(bins=[0])
        path = first.cache_path
        path.write_bytes(path.read_bytes()[:100])           # truncated: a disk that filled mid-write
        with pytest.warns(CacheWarning, match="unusable"):
            again = PSFLibrary.open(lens, TINY, GRID, cache_dir=tmp_path)
        assert again.ensure(bins=[0]) == [0]
    np.testing.assert_array_equal(again.psf[0], first.psf[0])


# ------------------------------------------------------------------ 5. pictures without matplotlib
@pytest.fixture
def no_matplotlib(monkeypatch):
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)       # `import matplotlib` fails as uninstalled


def test_require_matplotlib_names_the_option(no_matplotlib):
    from dcdi_core.render.pictures import PackageMissingError, require_matplotlib
    with pytest.raises(PackageMissingError, match="--png needs matplotlib.*pip install matplotlib"):
        require_matplotlib("--png")
    with pytest.raises(ImportError):                # what a caller of an import expects
        require_matplotlib("--png")


@pytest.mark.parametrize("command", ["bokeh", "dof", "psf", "psflib-show-lens", "psflib-show-file"])
def test_a_picture_without_matplotlib_is_refused_before_any_work(scene, capsys, no_matplotlib, command):
    rgbd = ["--image", scene / "aif.exr", "--depth", scene / "depth.exr", "-o", scene / "o.exr", *QUICK]
    argv, option = {
        "bokeh": (["bokeh", "--lens", "mos-s2", "--focus", "2", *rgbd, "--side-by-side", scene / "s.png"],
                  "--side-by-side"),
        "dof": (["dof", "--lens", "mos-s2", "--camera", "none", "--keep", "1", "2", *rgbd,
                 "--side-by-side", scene / "s.png"], "--side-by-side"),
        "psf": (["psf", "mos-s2", "--depth", "1", "--field", "0", "--png", scene / "s.png", *QUICK], "--png"),
        "psflib-show-lens": (["psflib", "show", "mos-s2", "--png", scene / "s.png", *QUICK], "--png"),
        "psflib-show-file": (["psflib", "show", scene / "missing.npz", "--png", scene / "s.png"], "--png"),
    }[command]
    code, out, err = run_cli(capsys, *argv)
    _one_line_refusal(code, err, f"{option} needs matplotlib", "pip install matplotlib")
    assert not (scene / "cache").exists() and not (scene / "o.exr").exists() and not (scene / "s.png").exists()


def test_a_ray_map_with_absurd_finite_coefficients_is_refused_at_load(tmp_path):
    """A ray map whose coefficients are finite but scaled by 1e30 (its
    checksum made anew) is refused when loaded, naming the file and the
    array, before any position is served (it once ended in an OverflowError)."""
    from dcdi_core.errors import DcdiError
    from dcdi_core.psf.raymap import RayMap
    src = ROOT / "dcdi_core" / "psf" / "data" / "raymap" / "zeiss-sonnar-50mm-f1-5.npz"
    rm = RayMap.load(src)
    arrays = dict(rm.arrays)
    arrays["xy"] = (arrays["xy"].astype(np.float64) * 1e30).astype(np.float32)
    assert np.isfinite(arrays["xy"]).all()
    RayMap(rm.meta, arrays).save(tmp_path / "absurd.npz")
    with pytest.raises(DcdiError, match=r"absurd\.npz.*xy"):
        RayMap.load(tmp_path / "absurd.npz")


def test_a_lens_length_of_1e300_is_refused_at_load(tmp_path):
    """A thickness, a semi-diameter or an asphere's sag over its aperture
    beyond a kilometre is refused naming the file, the surface and the
    field (a thickness of 1e300 once gave a traceback in one verb and a
    map of NaN in another)."""
    import re
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.optics.errors import LensFileError
    text = (ROOT / "lenses" / "mos-s1.toml").read_text()
    for pattern, value, fieldname in ((r"^thickness_mm = [0-9.]+", "thickness_mm = 1e300", "thickness_mm"),
                                      (r"^semi_diameter_mm = [0-9.]+", "semi_diameter_mm = 1e300",
                                       "semi_diameter_mm")):
        f = tmp_path / f"{fieldname}.toml"
        f.write_text(re.sub(pattern, value, text, count=1, flags=re.M))
        with pytest.raises(LensFileError, match=rf"{fieldname}.*out of range"):
            load_lens(f)


def test_a_ray_map_with_no_usable_source_is_refused(tmp_path):
    """A ray map whose sources are all marked unreachable is neither written
    nor read (it served empty kernels at every field and depth)."""
    from dcdi_core.errors import DcdiError
    from dcdi_core.psf.raymap import RayMap
    rm = RayMap.load(ROOT / "dcdi_core" / "psf" / "data" / "raymap" / "zeiss-sonnar-50mm-f1-5.npz")
    arrays = dict(rm.arrays, ok=np.zeros_like(rm.arrays["ok"]))
    with pytest.raises(DcdiError, match="no usable source"):
        RayMap(rm.meta, arrays).save(tmp_path / "none.npz")
    assert not (tmp_path / "none.npz").exists()
    # written by another hand (the checksum made anew): refused when read
    from dcdi_core.io.npzfile import write_format
    from dcdi_core.psf import raymap as R
    write_format(tmp_path / "none.npz", rm.meta, {k: np.asarray(v) for k, v in arrays.items()}, R.FORMAT,
                 R.FORMAT_VERSION)
    with pytest.raises(DcdiError, match="none.npz.*usable"):
        RayMap.load(tmp_path / "none.npz")
