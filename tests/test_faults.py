"""Nothing lost, nothing half-written: the fault cases a new user met, each
at its shared mechanism (the factory's folder lock, the signal policy, dead
runs' temporaries, the noise's range, the depth pixels a job masks or
clamps, an output that is an input)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import write_rgbd_scene
from dcdi_core.cli import main

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]
LEAVES = ["--recipe", "leaves", "--lens", "mos-s1", "--seed", "0", "--resolution", "24", "32", "--psf-rays", "12",
          "--psf-wavelengths", "3"]


def _cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 32, 48)
    return tmp_path


# ------------------------------------------------------------------ an output that is an input
@pytest.mark.parametrize("command, out_name", [("simulate", "aif.exr"), ("simulate", "depth.exr"),
                                               ("bokeh", "aif.exr"), ("correct", "aif.exr")])
def test_an_output_that_is_an_input_is_refused_before_any_work(scene, capsys, command, out_name):
    d = scene
    before = (d / out_name).read_bytes()
    extra = {"simulate": ["--lens", "mos-s1"], "bokeh": ["--lens", "mos-s1", "--focus", "1.5"],
             "correct": ["--lens", "mos-s1", "--method", "deconv"]}[command]
    # the same file by another spelling of its path
    code, _, err = _cli(capsys, command, "--image", d / "aif.exr", "--depth", d / "depth.exr", *extra,
                        "-o", d / "." / out_name, *FAST)
    assert code == 2 and err.count("\n") == 1 and "a file other than the input" in err, err
    assert (d / out_name).read_bytes() == before and not (d / "cache").exists()


def test_an_output_linked_to_an_input_is_refused(scene, capsys):
    d = scene
    os.link(d / "aif.exr", d / "hard.exr")
    code, _, err = _cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens",
                        "mos-s1", "-o", d / "hard.exr", *FAST)
    assert code == 2 and "--image" in err


# ------------------------------------------------------------------ the noise's range
def test_a_pixel_beyond_any_exposure_is_refused_not_a_traceback(tmp_path, monkeypatch, capsys):
    from dcdi_core.io.images import read_image, write_image
    write_rgbd_scene(tmp_path, monkeypatch, 32, 48)
    img = read_image(tmp_path / "aif.exr")
    img[3, 4] = 1e30
    write_image(tmp_path / "hot.exr", img)
    code, _, err = _cli(capsys, "simulate", "--image", tmp_path / "hot.exr", "--depth", tmp_path / "depth.exr",
                        "--lens", "mos-s1", "--noise", "--seed", "1", "-o", tmp_path / "out.exr", *FAST)
    assert code == 2 and "Traceback" not in err and "--image" not in err.split("error:")[0]
    assert "electrons" in err and not (tmp_path / "out.exr").exists(), err


def test_noise_settings_beyond_any_sensor_are_refused_by_the_engine_too():
    from dcdi_core.errors import InputRangeError
    from dcdi_core.render.noise import add_sensor_noise
    x = np.full((4, 4, 3), 0.5, np.float32)
    for kw, field in [({"full_well_electrons": 1e30}, "full_well_electrons"),
                      ({"read_noise_electrons": 1e30}, "read_noise_electrons")]:
        with pytest.raises(InputRangeError, match=field):
            add_sensor_noise(x, seed=0, **kw)
    with pytest.raises(InputRangeError, match="image"):
        add_sensor_noise(np.full((2, 2), 1e30), seed=0)
    assert np.isfinite(add_sensor_noise(x, seed=0, full_well_electrons=1e9, read_noise_electrons=1e3)).all()


# ------------------------------------------------------------------ depth pixels masked or clamped
def _holes(d: Path) -> Path:
    from dcdi_core.io.images import read_depth, write_depth
    depth = read_depth(d / "depth.exr")
    depth[:4, :8] = np.nan                   # 32 holes, as real ground truth has
    depth[-2:, -3:] = 0.3                    # 6 pixels nearer than the PSFs' 0.7 m
    write_depth(d / "holes.exr", depth)
    return d / "holes.exr"


@pytest.mark.parametrize("command, extra", [("simulate", ["--lens", "mos-s1"]),
                                            ("bokeh", ["--lens", "mos-s1", "--focus", "1.5"]),
                                            ("correct", ["--lens", "mos-s1", "--method", "deconv"]),
                                            ("dof", ["--camera", "mos-s1", "--lens", "6p", "--method", "deconv",
                                                     "--keep", "1", "2"])])
def test_masked_and_clamped_depth_pixels_are_counted_and_said(scene, capsys, command, extra):
    d = scene
    code, out, err = _cli(capsys, command, "--image", d / "aif.exr", "--depth", _holes(d), *extra,
                          "-o", d / "out.exr", *FAST)
    assert code == 0, err
    info = json.loads(out)
    counts = info.get("correction", info)
    assert counts["invalid_depth_pixels"] == 32 and counts["near_clamped_pixels"] == 6, counts
    assert "32 of 1536 pixels (2 %) have no valid depth" in err, err
    assert "6 of 1536 pixels (0.39 %) are nearer than 0.7 m" in err, err


def test_a_clean_depth_map_says_nothing(scene, capsys):
    d = scene
    code, out, err = _cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens",
                          "mos-s1", "-o", d / "out.exr", *FAST)
    assert code == 0 and "valid depth" not in err and "near limit" not in err
    assert json.loads(out)["invalid_depth_pixels"] == 0


# ------------------------------------------------------------------ signals and temporaries
_SLOW_WRITE = """
import os, sys, time
real = os.replace
def slow(src, dst):
    if str(dst).endswith("o.exr"):          # the output, not the PSF cache
        print("WRITING", file=sys.stderr, flush=True)
        time.sleep(60)
    real(src, dst)
os.replace = slow
from dcdi_core.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("sig, code, word", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_a_signal_during_the_write_leaves_nothing(scene, sig, code, word):
    d = scene
    env = dict(os.environ, DCDI_CACHE_DIR=str(d / "cache"))
    p = subprocess.Popen([sys.executable, "-c", _SLOW_WRITE, "simulate", "--image", str(d / "aif.exr"), "--depth",
                          str(d / "depth.exr"), "--lens", "mos-s1", "-o", str(d / "out" / "o.exr"), *FAST],
                         stderr=subprocess.PIPE, text=True, env=env, cwd=d)
    lines = []
    for line in p.stderr:
        lines.append(line)
        if line.startswith("WRITING"):
            break
    assert lines and lines[-1].startswith("WRITING"), "".join(lines)
    assert [x for x in os.listdir(d / "out") if ".tmp" in x]           # the temporary, being written
    p.send_signal(sig)
    rest = p.stderr.read()
    assert p.wait(timeout=60) == code
    assert rest.strip().splitlines()[-1] == f"dcdi: {word}" and "Traceback" not in rest, rest
    assert os.listdir(d / "out") == []                                # no temporary, no output


def test_a_dead_runs_temporary_is_removed_by_the_next_run(scene, capsys):
    from dcdi_core import atomic
    d = scene
    (d / "out").mkdir()
    dead = d / "out" / f".o.exr.p999999_h{atomic._HOST}_abcdef12.tmp.exr"     # no such process
    dead.write_bytes(b"half a file")
    old_foreign = d / "out" / ".o.exr.p1_h00000000_abcdef12.tmp.exr"        # another host, long untouched
    old_foreign.write_bytes(b"x")
    os.utime(old_foreign, (time.time() - 2 * 86400,) * 2)
    live = d / "out" / f".o.exr.p{os.getpid()}_h{atomic._HOST}_abcdef12.tmp.exr"   # a live run's
    live.write_bytes(b"x")
    code, _, err = _cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens",
                        "mos-s1", "-o", d / "out" / "o.exr", *FAST)
    assert code == 0, err
    assert not dead.exists() and not old_foreign.exists() and live.exists()


# ------------------------------------------------------------------ the factory
def test_a_factory_run_that_loses_the_folder_never_removes_it(tmp_path, monkeypatch):
    """Two runs start together on one --out: this one creates the folder, the
    other takes its lock first and writes; this one is refused and must
    leave the other's data alone."""
    import fcntl

    from blender_addon.factory import batch
    out = tmp_path / "data"
    real_lock = batch._lock
    held = []

    def other_run_first(folder):
        (folder / "dataset.json").write_text("the other run's")
        fd = os.open(folder, os.O_RDONLY)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.append(fd)
        return real_lock(folder)

    monkeypatch.setattr(batch, "_lock", other_run_first)
    try:
        assert batch.run([*LEAVES, "--count", "1", "--out", str(out)]) == 2
    finally:
        for fd in held:
            os.close(fd)
    assert (out / "dataset.json").read_text() == "the other run's"


def test_a_failed_run_removes_the_folder_it_made(tmp_path, monkeypatch):
    from blender_addon.factory import batch

    def broken(a, out):
        raise MemoryError
    monkeypatch.setattr(batch, "_run", broken)
    assert batch.run([*LEAVES, "--count", "1", "--out", str(tmp_path / "new")]) == 2
    assert not (tmp_path / "new").exists()


def test_ctrl_c_on_the_factory_is_one_line_and_resumes(tmp_path):
    out = tmp_path / "data"
    env = dict(os.environ, DCDI_CACHE_DIR=str(tmp_path / "cache"))
    p = subprocess.Popen([sys.executable, "-m", "blender_addon.factory", *LEAVES, "--count", "200", "--out",
                          str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    for line in p.stdout:
        if "samples/h" in line:               # a sample is finished
            break
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("factory: interrupted"), err
    done = [json.loads(x)["id"] for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert done and all((out / "aif" / f"{i}.exr").exists() for i in done)
    assert not [p for p in out.rglob(".*.tmp*")]


# ------------------------------------------------------------------ a prescription whose surfaces cross
CROSSED = """schema_version = 1
id = "crossed"
name = "a biconvex lens thinner at the centre than its curvatures allow"
[sensor]
semi_diagonal_mm = 2.0
[[surface]]
radius_mm = 5.0
thickness_mm = 0.5
material = "N-BK7"
semi_diameter_mm = 4.0
stop = true
[[surface]]
radius_mm = -5.0
thickness_mm = 4.5
material = "air"
semi_diameter_mm = 4.0
"""


def test_a_lens_whose_surfaces_cross_is_refused_naming_the_surface(tmp_path, capsys):
    (tmp_path / "crossed.toml").write_text(CROSSED)
    for argv in (["lens", "info", tmp_path / "crossed.toml"],
                 ["psf", tmp_path / "crossed.toml", "--field", "0", "--depth", "2", *FAST[:-2]]):
        code, out, err = _cli(capsys, *argv)
        assert code == 2 and out == "" and err.count("\n") == 1, err
        assert "surface 1, field 'thickness_mm'" in err and "cross: -3.5 mm apart at 4 mm" in err, err
    # the same lens with room for its edge loads
    (tmp_path / "ok.toml").write_text(CROSSED.replace("thickness_mm = 0.5", "thickness_mm = 4.2"))
    code, out, _ = _cli(capsys, "lens", "info", tmp_path / "ok.toml", "--json")
    assert code == 0 and json.loads(out)["id"] == "crossed"


def test_first_order_figures_the_rays_cannot_give_are_null_not_sentinels():
    from dcdi_core.optics.report import _figure
    assert _figure(-1.0) is None and _figure(float("inf")) is None and _figure(float("nan")) is None
    assert _figure(4.99) == 4.99


# ------------------------------------------------------------------ an image too large for the memory
@pytest.mark.parametrize("command, extra", [("simulate", []), ("bokeh", ["--focus", "1.5"]),
                                            ("correct", ["--method", "deconv"]),
                                            ("dof", ["--camera", "mos-s1", "--method", "deconv", "--keep", "1", "2"])])
def test_an_image_too_large_for_the_memory_is_refused_before_its_pixels_are_read(tmp_path, capsys, monkeypatch,
                                                                                 command, extra):
    """A 20000 x 20000 image (its header's size: the test's header says so)
    is refused from the header alone, with the figure; no pixel is read."""
    from dcdi_core.io import image_checks, images
    big = tmp_path / "huge.exr"
    images.write_image(big, np.zeros((16, 16, 3), np.float32))
    monkeypatch.setattr(image_checks, "image_size", lambda path, **k: (20000, 20000))
    read = []
    monkeypatch.setattr(images, "read_image", lambda *a, **k: read.append(a) or np.zeros((1, 1, 3)))
    lens = ["--lens", "6p"] if command == "dof" else ["--lens", "mos-s1"]
    code, out, err = _cli(capsys, command, "--image", big, "--depth", big, *lens, *extra, "-o", tmp_path / "o.exr")
    assert code == 2 and not read and err.count("\n") == 1, err
    assert "huge.exr: 20000 x 20000 px" in err and "GiB of memory" in err and "are free" in err, err


def test_a_host_applications_own_signal_handler_is_left_alone(monkeypatch):
    """Blender installs its SIGINT handler outside Python (getsignal: None);
    an ignored signal stays ignored: the policy touches neither."""
    from dcdi_core import signals
    seen = {}
    monkeypatch.setattr(signals.signal, "getsignal", lambda s: None if s == signal.SIGINT else signal.SIG_IGN)
    monkeypatch.setattr(signals.signal, "signal", lambda s, h: seen.setdefault(s, h))
    with signals.stop_on_signals():
        pass
    assert seen == {}


def test_an_afocal_prescription_is_refused_in_one_line(tmp_path, capsys):
    """A flat window (zero power): a project error naming the file, never a traceback."""
    flat = CROSSED.replace("radius_mm = 5.0", "radius_mm = inf").replace("radius_mm = -5.0", "radius_mm = inf")
    flat = flat.replace("thickness_mm = 0.5", "thickness_mm = 2.0")
    (tmp_path / "flat.toml").write_text(flat)
    for argv in (["lens", "info", tmp_path / "flat.toml"],
                 ["psf", tmp_path / "flat.toml", "--field", "0", "--depth", "2", *FAST[:-2]]):
        code, out, err = _cli(capsys, *argv)
        assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err
        assert "flat.toml" in err and "afocal" in err, err
