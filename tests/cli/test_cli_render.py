"""`dcdi simulate` and `dcdi bokeh` on files, as a user runs them."""
import json

import numpy as np
import pytest

from conftest import write_rgbd_scene

from dcdi_core.cli import main
from lab.cli import main as lab_main
from dcdi_core.io.images import read_image, write_depth, write_image
from dcdi_core.render.synthetic import synthetic_rgbd

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    img, depth = write_rgbd_scene(tmp_path, monkeypatch, 48, 72)
    return tmp_path, img


def test_simulate_writes_exr_and_reports(scene, capsys):
    d, img = scene
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s1",
                 "-o", str(d / "sim.exr"), "--sharp-out", str(d / "sharp.exr"), "--noise", "--seed", "3", *FAST])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["depth_aware"] and info["noise"]["seed"] == 3 and info["perturbation"] is None
    out = read_image(d / "sim.exr")
    assert out.shape == img.shape and np.isfinite(out).all()
    assert read_image(d / "sharp.exr").shape == img.shape


def test_simulate_with_perturbed_lens_records_it(scene, capsys):
    d, img = scene
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s2",
                 "-o", str(d / "p.exr"), "--perturb", "7", "--no-distortion", *FAST])
    assert code == 0
    rec = json.loads(capsys.readouterr().out)["perturbation"]
    assert rec["seed"] == 7 and rec["changes"]


def test_bokeh_focus_distance(scene, capsys):
    d, img = scene
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--focus", "2", "-o", str(d / "f.exr"), *FAST])
    assert code == 0 and read_image(d / "f.exr").shape == img.shape


def test_bokeh_png_and_side_by_side(scene, capsys):
    d, img = scene
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--keep", "1.1", "1.3", "-o", str(d / "b.png"), "--side-by-side", str(d / "side.png"), *FAST])
    assert code == 0
    assert (d / "b.png").read_bytes()[:4] == b"\x89PNG" and (d / "side.png").exists()


def test_mismatched_depth_is_a_clear_error(scene, capsys):
    d, img = scene
    write_depth(d / "small.exr", np.ones((10, 10), np.float32))
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "small.exr"), "--lens", "mos-s1",
                 "-o", str(d / "x.exr"), *FAST])
    assert code == 2 and "small.exr" in capsys.readouterr().err
    assert not (d / "x.exr").exists()


@pytest.mark.slow
def test_simulation_accuracy_report_quick(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    code = lab_main(["report", "simulation-accuracy", "--quick", "--out", str(tmp_path)])
    assert code == 0
    md = (tmp_path / "simulation-accuracy-mos-s1.md").read_text()
    assert "per-pixel reference" in md and "occlusion-aware layers" in md
    assert "Deposit width against rays" in md and "warp, then blur at the real positions" in md
    assert "Low-rank tiles" in md and "| lowrank | 0.005 |" in md
    assert "Multi-resolution bokeh against the exact path" in md and "| layered | exact (None) |" in md
    assert "Fast paths of the simulation" in md and "| fast |" in md


@pytest.mark.slow
def test_bench_render_quick(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["bench", "render", "--quick"])
    assert code == 0
    out = capsys.readouterr().out
    assert "baseline" in out and "peak memory" in out and "low-rank tiles" in out
    assert "multi-resolution bokeh" in out and "occlusion-aware" in out
    assert "simulation paths (issue 15" in out and "numpy-only" in out


def _run(d, command, *extra, lens="mos-s1", out="o.exr"):
    return main([command, "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", lens,
                 "-o", str(d / out), *FAST, *extra])


def test_simulate_accelerator_torch_equals_numpy(scene):
    pytest.importorskip("torch")
    d, img = scene
    assert _run(d, "simulate", "--no-distortion", out="np.exr") == 0
    assert _run(d, "simulate", "--no-distortion", "--accelerator", "torch", out="torch.exr") == 0
    assert np.abs(read_image(d / "np.exr") - read_image(d / "torch.exr")).max() <= 1e-5


def test_response_file_is_honoured_and_a_missing_one_is_refused(scene, capsys):
    d, img = scene
    (d / "flat.csv").write_text("wavelength_nm,r,g,b\n400,1,0,0\n500,1,1,0\n600,0,1,1\n700,0,0,1\n")
    assert _run(d, "simulate", "--no-distortion", out="default.exr") == 0
    assert _run(d, "simulate", "--no-distortion", "--response", str(d / "flat.csv"), out="flat.exr") == 0
    a, b = read_image(d / "default.exr"), read_image(d / "flat.exr")
    assert np.abs(a - b).max() > 1e-3          # another response, other PSFs
    capsys.readouterr()
    assert _run(d, "bokeh", "--focus", "2", "--response", str(d / "missing.csv"), out="m.exr") == 2
    err = capsys.readouterr().err
    assert "missing.csv" in err and "Traceback" not in err and not (d / "m.exr").exists()


def test_wavelength_gives_a_monochrome_simulation(scene, capsys):
    d, img = scene
    assert _run(d, "simulate", "--no-distortion", "--wavelength", "550", out="mono.exr") == 0
    grey = np.repeat(img.mean(axis=-1, keepdims=True), 3, axis=-1)
    write_image(d / "aif.exr", grey)
    assert _run(d, "simulate", "--no-distortion", "--wavelength", "550", out="mono_grey.exr") == 0
    out = read_image(d / "mono_grey.exr")
    # one PSF for all three channels: a grey scene stays grey
    assert np.abs(out[..., 0] - out[..., 1]).max() < 1e-5 and np.abs(out[..., 2] - out[..., 1]).max() < 1e-5


def test_bokeh_focus_prescribed_and_distort(scene, capsys):
    d, img = scene
    assert _run(d, "bokeh", "--focus", "prescribed", lens="6p", out="p.exr") == 0
    capsys.readouterr()
    assert _run(d, "bokeh", "--focus", "prescribed", "--distort", lens="6p", out="pd.exr") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["distortion"] is True
    p, pd = read_image(d / "p.exr"), read_image(d / "pd.exr")
    assert p.shape == pd.shape == img.shape and np.abs(p - pd).max() > 1e-3


def test_over_scan_frame_with_sensor_size_and_axis(scene, capsys):
    d, _ = scene
    img, depth = synthetic_rgbd(112, 144, seed=2)
    write_image(d / "aif.exr", img)
    write_depth(d / "depth.exr", depth)
    # a 112 x 144 over-scan render around a 48 x 64 sensor frame of 50 um pixels
    assert _run(d, "simulate", "--sensor-size", "48", "64", "--axis", "55.5", "71.5", "--image-pixel-pitch", "0.05",
                out="s.exr") == 0
    info = json.loads(capsys.readouterr().out)
    assert read_image(d / "s.exr").shape == (48, 64, 3) and info["border"] == "scene"
    assert info["not_imaged_pixels"] == 0          # the over-scan covers the distorted corners


@pytest.mark.parametrize("extra, says", [
    (["--sensor-size", "40", "80"], "--sensor-size"),
    (["--sensor-size", "40", "60", "--image-pixel-pitch", "0.5"], "--sensor-size"),
    (["--axis", "100", "5", "--image-pixel-pitch", "0.0122"], "--axis"),
    (["--pixel-pitch", "-0.01"], "--pixel-pitch"),     # one option (--image-pixel-pitch its other spelling)
    (["--image-pixel-pitch", "0.5"], "aif.exr"),
    (["--patch", "15"], "patch"),
    (["--interpolation", "cubic"], "invalid choice"),
])
def test_bad_geometry_options_are_refused_before_any_work(scene, capsys, extra, says):
    d, img = scene
    try:
        code = _run(d, "simulate", *extra, out="bad.exr")
    except SystemExit as e:                     # argparse's own refusals
        code = e.code
    err = capsys.readouterr().err
    assert code == 2 and says in err and "Traceback" not in err
    assert not (d / "bad.exr").exists() and not (d / "cache").exists()     # no PSF was built


def test_output_extension_is_refused_before_any_work(scene, capsys):
    d, img = scene
    assert _run(d, "simulate", "--sharp-out", str(d / "s.tiff"), out="x.exr") == 2
    assert "s.tiff" in capsys.readouterr().err and not (d / "cache").exists() and not (d / "x.exr").exists()


def test_bokeh_multires_flag_runs_and_refuses_a_bad_rule(scene, capsys):
    d, img = scene
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--keep", "1.1", "1.3", "-o", str(d / "m.exr"), "--multires", "0.5", "--max-level", "1", *FAST])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["multires"] == 0.5 and read_image(d / "m.exr").shape == img.shape
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--keep", "1.1", "1.3", "-o", str(d / "bad.exr"), "--multires", "-2", *FAST])
    assert code != 0 and "multires" in capsys.readouterr().err and not (d / "bad.exr").exists()


def test_bench_cli_quick_times_the_whole_processes(capsys):
    from dcdi_core.cli import main
    assert main(["bench", "cli", "--quick"]) == 0
    out = capsys.readouterr().out
    for job in ("dcdi --help (start-up)", "dcdi simulate", "dcdi bokeh --focus 1.5"):
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(job))
        assert " s (" in line and "s CPU" in line


def test_the_aperture_stops_bokeh_simulate_and_correct_down(scene, capsys):
    """--f-number and --blades on bokeh, simulate and correct: a stopped-down
    bokeh blurs less than wide open; a capture simulated stopped down records
    its stop, and correcting it at another stop says so; a wider stop than
    the lens's is one line before any work."""
    d, img = scene
    io = ["--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr")]
    for name, extra in (("wide", []), ("f8", ["--f-number", "8", "--blades", "6"])):
        assert main(["bokeh", *io, "--lens", "6p", "--focus", "1.2", "-o", str(d / f"{name}.exr"), *FAST,
                     *extra]) == 0
    capsys.readouterr()
    wide, f8 = read_image(d / "wide.exr"), read_image(d / "f8.exr")
    assert 0 < np.abs(f8 - img).mean() < 0.8 * np.abs(wide - img).mean()
    assert main(["simulate", *io, "--lens", "mos-s1", "--f-number", "8", "--blades", "6", "-o", str(d / "sim.exr"),
                 "--no-distortion", *FAST]) == 0
    capsys.readouterr()
    correct = ["correct", "--image", str(d / "sim.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s1",
               "--method", "deconv", *FAST]
    assert main([*correct, "-o", str(d / "c1.exr")]) == 0
    assert "stopped down (f/8, 6 blades), this job's mos-s1 is wide open" in capsys.readouterr().err
    assert main([*correct, "--f-number", "8", "--blades", "6", "-o", str(d / "c2.exr")]) == 0
    assert "stopped down" not in capsys.readouterr().err
    code = main(["bokeh", *io, "--lens", "6p", "--focus", "1.2", "-o", str(d / "x.exr"), "--f-number", "1.2"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "f/1.64" in err[0] and not (d / "x.exr").exists()


def test_bokeh_reports_its_error_budget_and_plan(scene, capsys):
    d, img = scene
    args = ["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens",
            "zeiss-sonnar-50mm-f1-5", "--focus", "2", "--kernel", "15"]
    assert main([*args, "-o", str(d / "q.exr"), "--quality", "30", "--rays", "20"]) == 0
    q = json.loads(capsys.readouterr().out)["quality"]
    # planned from the lens's error table: the rays given kept, the rest chosen, the error beside the seconds
    assert q["budget_db"] == 30 and q["pupil_samples"] == 20 and q["n_wavelengths"] < 31
    assert "error table" in q["plan"]
    assert main([*args, "-o", str(d / "full.exr"), "--quality", "full", *FAST[:4]]) == 0
    assert "quality" not in json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("bad", ["5", "nan", "high", "81"])
def test_a_budget_out_of_range_is_refused_before_any_work(scene, capsys, bad):
    d, img = scene
    with pytest.raises(SystemExit) as e:
        main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
              "--focus", "2", "-o", str(d / "x.exr"), "--quality", bad])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--quality" in err and "dB" in err and not (d / "x.exr").exists()


def test_bench_quality_needs_a_lens(capsys):
    assert main(["bench", "quality"]) == 2
    assert "dcdi bench quality LENS" in capsys.readouterr().err


def test_bokeh_reads_the_image_at_the_pinhole_focal_length_given(scene, capsys):
    """--pinhole-focal-length: a render from a camera framed as the lens at a
    close focus is read at that scale (the picture not zoomed twice); a bad
    one is refused by its option before any work."""
    d, img = scene
    assert _run(d, "bokeh", "--focus", "1.5", "--distort", lens="6p", out="own.exr") == 0
    capsys.readouterr()
    assert _run(d, "bokeh", "--focus", "1.5", "--distort", "--pinhole-focal-length", "22.6", lens="6p",
                out="framed.exr") == 0
    capsys.readouterr()
    own, framed = read_image(d / "own.exr"), read_image(d / "framed.exr")
    assert own.shape == framed.shape == img.shape and np.abs(own - framed).mean() > 1e-3
    for bad in ("-3", "0", "nan"):
        assert _run(d, "bokeh", "--focus", "1.5", "--pinhole-focal-length", bad, lens="6p", out="bad.exr") == 2
        err = capsys.readouterr().err
        assert "--pinhole-focal-length" in err and len(err.strip().splitlines()) == 1, err
    assert not (d / "bad.exr").exists()
