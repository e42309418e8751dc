"""The `dcdi` command's grammar and user-facing guarantees: the noun-verb
spellings (the old ones gone), `correct` with the shipped network (`dacn
correct`: the network alone, `correct --method dacn`), damaged model
files ending in one line, the depth-unit warning of `dof`, the generated
reference page, and the engine's render request the command builds."""
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conftest import write_rgbd_scene

from dcdi_core.cli import build_parser, main
from support.cli import run_cli
from dcdi_core.io.images import write_depth, write_image
from dcdi_core.shipped import network

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15"]
WEIGHTS = Path(__file__).resolve().parents[2] / "dcdi_core" / "models" / "weights"


_cli = run_cli


def _one_error_line(code, err, *says):
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err, err
    assert [x for x in lines if x.startswith("dcdi: error:")] == lines[-1:], err
    for s in says:
        assert s in lines[-1], lines[-1]
    return lines[-1]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 24, 32)
    return tmp_path


# ------------------------------------------------------------------ grammar
def test_dacn_correct_is_correct_with_the_network_and_its_options_only():
    p = build_parser()
    net = vars(p.parse_args(["dacn", "correct", "--image", "i", "-o", "o.exr"]))
    top = vars(p.parse_args(["correct", "--image", "i", "-o", "o.exr", "--method", "dacn"]))
    assert net["func"] is top["func"] and net["method"] == top["method"] == "dacn"
    assert vars(p.parse_args(["correct", "--image", "i", "-o", "o.exr"]))["method"] == "auto"
    own = ("command", "dacn_command", "words", "files", "files_labels")      # each verb's own paths declared
    assert {k: v for k, v in top.items() if k in net and k not in own} == \
        {k: v for k, v in net.items() if k not in own}
    # the deconvolution's options and the PSF options are `dcdi correct`'s alone
    assert {"deconv_weight", "one_depth", "noise_full_well", "noise_read", "image_pixel_pitch", "rays",
            "psf_source"} <= set(top) - set(net)


def test_the_old_spellings_are_gone_and_the_nouns_listed(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "\n    train" not in text and "\n    eval" not in text and "\n    report" not in text
    for noun in ("dacn", "olf", "depth", "correct", "dof", "dataset", "bench"):
        assert f"\n    {noun}" in text
    # the old spellings and the lab's reports (python -m lab report ...) are no verbs of the product
    for gone in (["train", "dacn", "--data", "d", "-o", "r"], ["eval", "run", "--data", "d"], ["report", "olf"]):
        with pytest.raises(SystemExit):
            build_parser().parse_args(gone)


# ------------------------------------------------------------------ correct with the shipped DACN
@pytest.mark.parametrize("verb", [["correct", "--method", "dacn"], ["dacn", "correct"]])
def test_correct_takes_the_shipped_dacn_of_the_lens(tmp_path, capsys, verb):
    pytest.importorskip("torch")
    import json
    shipped = network("dacn").shipped_keys()
    if "mos-s1" not in shipped:
        pytest.skip("no shipped DACN of mos-s1")
    write_image(tmp_path / "cap.exr", np.random.default_rng(0).uniform(0, 1, (20, 30, 3)).astype(np.float32))
    write_depth(tmp_path / "d.exr", np.full((20, 30), 2.0, np.float32))
    code, out, err = _cli(capsys, *verb, "--image", tmp_path / "cap.exr", "--depth", tmp_path / "d.exr",
                          "--lens", "mos-s1", "-o", tmp_path / "out.exr")
    assert code == 0, err
    info = json.loads(out)
    assert info["lens"] == "mos-s1" and info["correction"]["method"] == "dacn" and (tmp_path / "out.exr").exists()
    assert info["correction"]["model"].endswith("dacn-mos-s1.npz") and info["correction"]["trained_for"] == "mos-s1"
    assert "dcdi: correction by the network (DACN)" in err
    code, _, err = _cli(capsys, *verb, "--image", tmp_path / "cap.exr", "--depth", tmp_path / "d.exr",
                        "--lens", "6p", "-o", tmp_path / "x.exr")
    _one_error_line(code, err, "no shipped DACN for lens 6p", ", ".join(shipped), "--model")
    code, _, err = _cli(capsys, *verb, "--image", tmp_path / "cap.exr", "--depth", tmp_path / "d.exr",
                        "-o", tmp_path / "x.exr")
    _one_error_line(code, err, "--lens is missing", "--model")
    assert not (tmp_path / "x.exr").exists()


# ------------------------------------------------------------------ damaged model files
def _damaged(tmp_path) -> dict:
    """{kind: path} of model files a user might hand over by mistake."""
    good = (WEIGHTS / "dacn-mos-s1.npz").read_bytes() if (WEIGHTS / "dacn-mos-s1.npz").exists() else None
    files = {}
    if good is not None:
        files["truncated"] = tmp_path / "truncated.npz"
        files["truncated"].write_bytes(good[: len(good) // 2])
        flipped = bytearray(good)
        flipped[len(good) // 3: len(good) // 3 + 64] = bytes(64)
        files["corrupt"] = tmp_path / "corrupt.npz"
        files["corrupt"].write_bytes(bytes(flipped))
    files["random"] = tmp_path / "random.npz"
    files["random"].write_bytes(np.random.default_rng(0).bytes(4000))
    files["zip"] = tmp_path / "zip.npz"
    with zipfile.ZipFile(files["zip"], "w") as z:
        z.writestr("readme.txt", "not arrays")
    files["empty"] = tmp_path / "empty.npz"
    files["empty"].write_bytes(b"")
    return files


def test_the_runtime_readers_turn_any_damage_into_a_model_file_error(tmp_path):
    from dcdi_core.errors import ModelFileError
    from dcdi_core.io.model_npz import read_model_npz
    from dcdi_core.psf.olf import read_olf_file
    for path in _damaged(tmp_path).values():
        for read in (read_olf_file, lambda p: read_model_npz(p, "dcdi-dacn", 1, "DACN")):
            with pytest.raises(ModelFileError, match=path.name):
                read(path)


@pytest.mark.parametrize("command", ["olf info", "simulate --olf", "bokeh --olf", "psf --olf", "correct --model",
                                     "dof --dacn", "dof --depth-checkpoint"])
def test_a_damaged_model_file_ends_in_one_line_naming_it(scene, capsys, command):
    d = scene
    if command.startswith(("correct", "dof")):
        pytest.importorskip("torch")
    files = _damaged(d)
    if "dof" in command or "olf" in command:     # the wrong kind of file too: a DACN for an OLF, ...
        wrong = WEIGHTS / ("depth-mos-s1.npz" if command == "dof --dacn" else "dacn-mos-s1.npz")
        if wrong.exists():
            files["wrong format"] = wrong
    rgbd = ["--image", d / "aif.exr", "--depth", d / "depth.exr"]
    for kind, path in files.items():
        argv = {"olf info": ["olf", "info", path],
                "simulate --olf": ["simulate", *rgbd, "--lens", "mos-s1", "-o", d / "o.exr", "--olf", path, *FAST],
                "bokeh --olf": ["bokeh", *rgbd, "--lens", "6p", "--focus", "2", "-o", d / "o.exr", "--olf", path,
                                *FAST],
                "psf --olf": ["psf", "mos-s1", "--field", "0.5", "--depth", "2", "--olf", path, *FAST],
                "correct --model": ["correct", *rgbd, "--model", path, "-o", d / "o.exr"],
                "dof --dacn": ["dof", *rgbd, "--lens", "6p", "--keep", "1", "2", "--camera", "mos-s1", "--dacn", path,
                               "-o", d / "o.exr", *FAST],
                "dof --depth-checkpoint": ["dof", "--image", d / "aif.exr", "--lens", "6p", "--keep", "1", "2",
                                           "--camera", "none", "--depth-checkpoint", path, "-o", d / "o.exr",
                                           *FAST]}[command]
        code, _, err = _cli(capsys, *argv)
        _one_error_line(code, err, path.name)
        assert not (d / "o.exr").exists(), kind
        assert not (d / "cache").exists(), f"{kind}: a PSF was traced before the file was refused"


# ------------------------------------------------------------------ dof warns about depth units
def test_dof_warns_about_a_depth_map_in_millimetres(scene, capsys):
    pytest.importorskip("torch")
    d = scene
    from dcdi_core.io.images import read_depth
    write_depth(d / "mm.exr", read_depth(d / "depth.exr") * 1000.0)
    code, _, err = _cli(capsys, "dof", "--image", d / "aif.exr", "--depth", d / "mm.exr", "--lens", "6p",
                        "--keep", "1", "2", "--camera", "none", "-o", d / "o.exr", "--psf-source", "trace", *FAST)
    assert code == 0, err
    warn = [x for x in err.splitlines() if x.startswith("dcdi: warning:")]
    assert len(warn) == 1 and "mm.exr" in warn[0] and "the likely unit is mm" in warn[0]


# ------------------------------------------------------------------ the reference page
def test_docs_cli_md_is_the_generated_reference():
    from lab.cli_reference import DOC, reference
    text = reference()
    assert DOC.read_text(encoding="utf-8") == text, \
        "docs/cli.md is out of date: run python -m lab cli-reference --write"
    for command in ("dcdi dacn train", "dcdi olf info", "dcdi depth export", "dcdi correct", "--image-pixel-pitch"):
        assert command in text


# ------------------------------------------------------------------ the engine's request
def test_render_request_is_checked_from_plain_values_before_any_image():
    from dcdi_core.cli.common import WORDS
    from dcdi_core.errors import InputRangeError
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.request import RenderRequest
    lens = load_lens("mos-s1")
    for kw, says in [({"patch": 15}, "--patch = 15"), ({"interpolation": "cubic"}, "--interpolation"),
                     ({"noise": True}, "--seed is missing"), ({"fixed_depth_m": 0.1}, "--fixed-depth = 0.1"),
                     ({"perturb_seed": 1, "perturb_fraction": 0.9}, "--perturb-fraction"),
                     ({"psf": PSFSettings(wavelength_nm=250.0)}, "--wavelength"),
                     ({"image_pixel_pitch_mm": 0.01, "psf": PSFSettings(pixel_pitch_mm=0.02)}, "--pixel-pitch")]:
        with pytest.raises(InputRangeError) as e:
            RenderRequest(lens=lens, **kw)
        # the engine names the request's field; the command shows it as its option
        assert says in e.value.in_words(WORDS), e.value.in_words(WORDS)
    # the add-on names the settings in its own words
    with pytest.raises(InputRangeError, match="Patch size = 15"):
        RenderRequest(lens=lens, patch=15, labels={"patch": "Patch size"})


def test_render_request_plans_an_over_scan_frame():
    from dcdi_core.cli.common import WORDS
    from dcdi_core.errors import InputRangeError
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.request import RenderRequest
    lens = load_lens("mos-s1")
    over_scan = RenderRequest(lens=lens, sensor_size=(48, 64), axis_px=(55.5, 71.5), image_pixel_pitch_mm=0.05)
    plan = over_scan.plan(112, 144)
    assert (plan.geometry.height, plan.geometry.width) == (48, 64)
    assert plan.source_geometry.center_px == (55.5, 71.5) and plan.settings.pixel_pitch_mm is None
    whole = RenderRequest(lens=lens).plan(48, 64)
    assert whole.source_geometry is None and 0.95 < whole.geometry.max_field <= 1.0   # pixel centres
    with pytest.raises(InputRangeError, match="sensor_size") as e:
        RenderRequest(lens=lens, sensor_size=(200, 64)).plan(112, 144)
    assert "--sensor-size" in e.value.in_words(WORDS)
    with pytest.raises(InputRangeError, match="axis_px") as e:
        RenderRequest(lens=lens, axis_px=(5.0, 5.0)).plan(112, 144)
    assert "--axis" in e.value.in_words(WORDS)
