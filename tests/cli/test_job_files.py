"""Every path a verb writes is declared before any work, checked against
every input in one place (``outputs.JobFiles``), and the outputs appear
together or not at all."""
import argparse
import errno
import os
from pathlib import Path

import numpy as np
import pytest

from conftest import write_rgbd_scene
from support.cli import run_cli as _cli
from dcdi_core.atomic import atomic_path, write_text
from dcdi_core.cli import build_parser
from dcdi_core.cli.files import NOT_PATHS, SPECS, leaves
from dcdi_core.errors import DcdiError, InputRangeError, OutputError
from dcdi_core.outputs import JobFiles, UndeclaredOutputError

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 32, 48)
    return tmp_path


def _temporaries(folder: Path):
    return sorted(p.name for p in folder.rglob(".*") if ".tmp" in p.name)


# ------------------------------------------------------------------ the declarations
def _dests(parser):
    return {a.dest for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) and a.dest != argparse.SUPPRESS}


def test_every_verb_declares_every_option_that_names_a_path():
    """Each option of each verb is an input, an output file, an output folder
    or in NOT_PATHS: a new option must say which before it can land."""
    verbs = list(leaves(build_parser()))
    assert len(verbs) >= 25
    for words, parser in verbs:
        spec = SPECS.get(words)
        assert spec is not None, f"dcdi {' '.join(words)} declares no files (cli/files.py SPECS)"
        declared = set(spec.reads) | set(spec.writes) | set(spec.into)
        dests = _dests(parser)
        unknown = dests - declared - NOT_PATHS - set(spec.others)
        assert not unknown, f"dcdi {' '.join(words)}: options {sorted(unknown)} are not classified"
        stale = declared - dests
        assert not stale, f"dcdi {' '.join(words)}: SPECS names {sorted(stale)}, which it does not have"


def test_the_declaration_check_catches_an_unclassified_option(monkeypatch):
    """Planted: a new output option nobody declared fails the walk above."""
    p = build_parser()
    words, parser = next((w, q) for w, q in leaves(p) if w == ("bokeh",))
    parser.add_argument("--depth-out", default=None)
    unknown = _dests(parser) - set(SPECS[words].reads) - set(SPECS[words].writes) - NOT_PATHS
    assert unknown == {"depth_out"}


# ------------------------------------------------------------------ outputs that are inputs
def test_a_confidence_map_over_the_capture_is_refused(scene, capsys):
    before = (scene / "aif.exr").read_bytes()
    code, _, err = _cli(capsys, "depth", "estimate", "--image", scene / "aif.exr", "--camera", "mos-s1",
                        "-o", scene / "d.exr", "--confidence", scene / "aif.exr", *FAST)
    assert code == 2 and err.count("\n") == 1 and "--confidence" in err and "--image" in err, err
    assert (scene / "aif.exr").read_bytes() == before and not (scene / "cache").exists()


def test_an_intermediate_over_the_capture_is_refused(scene, capsys):
    inter = scene / "inter"
    inter.mkdir()
    os.replace(scene / "aif.exr", inter / "corrected.exr")
    before = (inter / "corrected.exr").read_bytes()
    code, _, err = _cli(capsys, "dof", "--image", inter / "corrected.exr", "--depth", scene / "depth.exr",
                        "--camera", "mos-s1", "--method", "deconv", "--lens", "mos-s1", "--focus", "1.5",
                        "-o", scene / "out.exr", "--save-intermediates", inter, *FAST)
    assert code == 2 and "--save-intermediates" in err and "--image" in err, err
    assert (inter / "corrected.exr").read_bytes() == before and not (scene / "cache").exists()


def test_an_output_through_a_symbolic_link_is_refused(scene, capsys):
    os.symlink(scene / "depth.exr", scene / "link.exr")
    code, _, err = _cli(capsys, "bokeh", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--lens", "mos-s1", "--focus", "1.5", "-o", scene / "link.exr", *FAST)
    assert code == 2 and "--depth" in err, err


def test_two_outputs_onto_one_file_are_refused(scene, capsys):
    code, _, err = _cli(capsys, "depth", "estimate", "--image", scene / "aif.exr", "--camera", "mos-s1",
                        "-o", scene / "d.exr", "--confidence", scene / "." / "d.exr", *FAST)
    assert code == 2 and "--confidence" in err and "-o" in err, err


def test_an_output_folder_that_cannot_be_made_is_refused_before_any_work(scene, capsys):
    (scene / "afile").write_text("x")
    code, _, err = _cli(capsys, "dof", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--camera", "mos-s1", "--method", "deconv", "--lens", "mos-s1", "--focus", "1.5",
                        "-o", scene / "out.exr", "--save-intermediates", scene / "afile" / "sub", *FAST)
    assert code == 2 and "is a file, not a folder" in err, err
    assert not (scene / "cache").exists() and not (scene / "out.exr").exists()


def test_a_folder_where_the_sidecar_goes_is_refused_before_any_work(scene, capsys):
    (scene / "out.png.dcdi.json").mkdir()
    code, _, err = _cli(capsys, "simulate", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--lens", "mos-s1", "-o", scene / "out.png", *FAST)
    assert code == 2 and "a folder stands where the file is to be written" in err, err
    assert not (scene / "cache").exists() and not (scene / "out.png").exists()


# ------------------------------------------------------------------ together, or none
def _fail_writing(monkeypatch, name: str):
    """Make the write of the file called ``name`` fail as a full disk does."""
    import dcdi_core.atomic as atomic
    real = atomic.atomic_path

    from contextlib import contextmanager

    @contextmanager
    def failing(path):
        with real(path) as tmp:
            if Path(path).name == name:
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
            yield tmp
    monkeypatch.setattr(atomic, "atomic_path", failing)
    import dcdi_core.io.images as images
    monkeypatch.setattr(images, "atomic_path", failing)
    import dcdi_core.io.capture_record as record
    monkeypatch.setattr(record, "atomic_path", failing)


def test_dof_on_a_full_disk_leaves_none_of_its_outputs(scene, capsys, monkeypatch):
    (scene / "out.exr").write_bytes(b"the user's earlier result")
    _fail_writing(monkeypatch, "side.png")
    code, _, err = _cli(capsys, "dof", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--camera", "mos-s1", "--method", "deconv", "--lens", "mos-s1", "--focus", "1.5",
                        "-o", scene / "out.exr", "--save-intermediates", scene / "inter",
                        "--side-by-side", scene / "side.png", *FAST)
    assert code == 2 and "no space left" in err, err
    assert (scene / "out.exr").read_bytes() == b"the user's earlier result"
    assert not (scene / "inter" / "corrected.exr").exists() and not (scene / "inter" / "depth.exr").exists()
    assert not (scene / "side.png").exists()
    assert _temporaries(scene) == []


def test_a_png_goes_with_its_sidecar_or_not_at_all(scene, capsys, monkeypatch):
    _fail_writing(monkeypatch, "out.png.dcdi.json")
    code, _, err = _cli(capsys, "simulate", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--lens", "mos-s1", "-o", scene / "out.png", *FAST)
    assert code == 2 and "no space left" in err, err
    assert not (scene / "out.png").exists() and _temporaries(scene) == []


def test_outputs_appear_together_when_the_job_succeeds(scene, capsys):
    code, _, err = _cli(capsys, "simulate", "--image", scene / "aif.exr", "--depth", scene / "depth.exr",
                        "--lens", "mos-s1", "-o", scene / "out.png", "--sharp-out", scene / "sharp.exr", *FAST)
    assert code == 0, err
    assert (scene / "out.png").is_file() and (scene / "out.png.dcdi.json").is_file()
    assert (scene / "sharp.exr").is_file() and _temporaries(scene) == []


def test_a_dead_runs_confidence_temporary_goes_with_the_next_run(scene, capsys):
    dead = scene / ".conf.exr.p999999999_h00000000_abcdef.tmp.exr"
    dead.write_bytes(b"half")
    os.utime(dead, (0, 0))                              # another host's, a day old: dead
    code, _, err = _cli(capsys, "depth", "estimate", "--image", scene / "aif.exr", "--camera", "mos-s1",
                        "-o", scene / "d.npy", "--confidence", scene / "conf.exr", "--refine", "none", *FAST)
    assert code == 0, err
    assert not dead.exists() and (scene / "conf.exr").is_file()
    assert np.load(scene / "d.npy").shape == (32, 48)          # -o DEPTH.npy, as the docs offer


# ------------------------------------------------------------------ the mechanism itself
def test_a_rename_that_fails_half_way_puts_back_what_it_replaced(tmp_path, monkeypatch):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    files = JobFiles().write(a, "-o").write(b, "--other")
    files.check()
    real_replace = os.replace

    def replace(src, dst):
        if Path(dst) == b:
            raise OSError(errno.EIO, "I/O error")
        return real_replace(src, dst)
    with pytest.raises(OutputError):
        with files.together():
            write_text(a, "new a")
            write_text(b, "new b")
            monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "replace", real_replace)
    assert a.read_text() == "old a" and not b.exists()
    assert _temporaries(tmp_path) == []


def test_nothing_is_renamed_when_the_job_fails(tmp_path):
    a = tmp_path / "a.txt"
    files = JobFiles().write(a, "-o")
    with pytest.raises(RuntimeError):
        with files.together():
            write_text(a, "new")
            raise RuntimeError("the job failed after writing")
    assert not a.exists() and _temporaries(tmp_path) == []


def test_an_undeclared_write_is_a_bug_the_tests_see(tmp_path, monkeypatch):
    monkeypatch.setenv("DCDI_CHECK_OUTPUTS", "1")
    files = JobFiles().write(tmp_path / "a.txt", "-o").write_into(tmp_path / "run", "--run")
    with files.together():
        write_text(tmp_path / "run" / "checkpoint.json", "{}")      # inside a declared folder: at once
        assert (tmp_path / "run" / "checkpoint.json").is_file()
        with pytest.raises(UndeclaredOutputError):
            write_text(tmp_path / "elsewhere.txt", "x")
    assert not (tmp_path / "elsewhere.txt").exists()


def test_a_write_onto_an_input_is_refused_when_it_happens(tmp_path):
    src = tmp_path / "run" / "data.json"
    src.parent.mkdir()
    src.write_text("input")
    files = JobFiles().read(src, "--data").write_into(tmp_path / "run", "-o")
    with pytest.raises(OutputError, match="--data"):
        with files.together():
            write_text(src, "over it")
    assert src.read_text() == "input"


# ------------------------------------------------------------------ a record's values, a bokeh's lens
def _capture_with_record(scene, **fields):
    from dcdi_core.io.capture_record import CaptureRecord
    from dcdi_core.io.images import read_image, write_image
    record = CaptureRecord(kind="simulated", lens_id="mos-s1", pixel_pitch_mm=0.0122, image_size=(32, 48), **fields)
    write_image(scene / "cap.exr", read_image(scene / "aif.exr"), record=record)
    return scene / "cap.exr"


@pytest.mark.parametrize("fields, blamed", [({"axis_px": (1e6, 5.0)}, "axis_px"),
                                            ({"focus_distance_m": 1e-6}, "focus_distance_m")])
def test_a_records_bad_value_is_blamed_on_the_record(scene, capsys, fields, blamed):
    cap = _capture_with_record(scene, **fields)
    code, _, err = _cli(capsys, "correct", "--image", cap, "--depth", scene / "depth.exr", "--lens", "mos-s1",
                        "--method", "deconv", "-o", scene / "out.exr", *FAST)
    assert code == 2 and f"capture record of the image {cap}: {blamed}" in err, err
    assert "--axis" not in err and "--focus" not in err


def test_a_bokeh_through_another_lens_than_the_captures_runs(scene, capsys):
    cap = _capture_with_record(scene)
    code, _, err = _cli(capsys, "bokeh", "--image", cap, "--depth", scene / "depth.exr", "--lens", "mos-s2",
                        "--focus", "1.5", "-o", scene / "out.exr", *FAST)
    assert code == 0, err
    assert "records a capture through mos-s1" in err


def test_depth_estimate_names_its_own_option_for_the_lens(scene, capsys):
    cap = _capture_with_record(scene)
    code, _, err = _cli(capsys, "depth", "estimate", "--image", cap, "--camera", "mos-s2", "-o", scene / "d.exr",
                        *FAST)
    assert code == 2 and "--camera" in err and "--lens" not in err, err
