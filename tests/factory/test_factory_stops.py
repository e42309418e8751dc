"""The factory stops cleanly at any stage and never leaves a sample
half-committed (pip bpy). A factory process is signalled while it pauses in
one stage of its second sample (stage_pause.py: inside Blender's render,
between the sample's files, before the simulation): exit 130 or 143, one
line, no traceback, no temporary, the first sample kept, and the same
command resumes to the bytes of an uninterrupted run. A full disk (ENOSPC
injected in the manifest's append or in an image's write) leaves the
sample absent, with a one-line error; an --out whose sample folders cannot
be written is refused before any render. On the code before these fixes a
stop inside the render was dropped by Blender (the run went on, exit 0)
and a stop or a full disk after the first files left them without a
manifest line."""
import errno
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

from blender_addon.factory import batch as factory  # noqa: E402
from blender_addon.factory import commit, samples  # noqa: E402
from blender_addon.factory.render import render_still  # noqa: E402
from dcdi_core import signals  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["--recipe", "tabletop", "--count", "2", "--lens", "mos-s1", "--seed", "5", "--resolution", "24", "32",
        "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]
SECOND = "tabletop-000001"
PAUSE = Path(__file__).resolve().parent / "stage_pause.py"
STOPPED = "factory: {}; the finished samples are kept: run the same command again to resume"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("psf-cache")


@pytest.fixture(autouse=True)
def _cache_env(cache, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(cache))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, cache):
    """An uninterrupted run of ARGS: what every resumed folder must equal."""
    out = tmp_path_factory.mktemp("reference") / "ds"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DCDI_CACHE_DIR", str(cache))
        assert factory.run([*ARGS, "--out", str(out)]) == 0
    return out


def _files(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*.exr"))}


def _ids(root: Path) -> list[str]:
    return [json.loads(x)["id"] for x in (root / "manifest.jsonl").read_text().splitlines()]


def _only_the_first_sample(out: Path) -> None:
    """The folder holds sample 0 whole, with its line, and nothing of sample 1, nor any temporary."""
    assert _ids(out) == ["tabletop-000000"]
    names = set(_files(out))
    assert len(names) == 5 and not any(SECOND in n for n in names), names
    assert list(out.rglob(".*")) == []                   # no temporary, no hand-over render


def stop_in(out: Path, stage: str, signum: int, pause_s: float = 3.0) -> subprocess.CompletedProcess:
    """Run the factory into ``out``, pausing ``pause_s`` seconds in ``stage``
    of the second sample; send ``signum`` once it says so (0.3 s later);
    returns the finished process with its stdout and stderr."""
    env = dict(os.environ, DCDI_TEST_STAGE_PAUSE=f"{stage} 2 {pause_s}")
    p = subprocess.Popen([sys.executable, str(PAUSE), "run", *ARGS, "--out", str(out)], cwd=ROOT,
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout = []
    reader = threading.Thread(target=lambda: stdout.extend(p.stdout), daemon=True)
    reader.start()
    err = []
    timer = None
    for line in p.stderr:
        err.append(line)
        if line.startswith("stage pause:") and timer is None:
            timer = threading.Timer(0.3, p.send_signal, [signum])
            timer.start()
    p.wait(timeout=300)
    reader.join(timeout=10)
    assert timer is not None, "".join(err)[-3000:]
    return subprocess.CompletedProcess(p.args, p.returncode, "".join(stdout), "".join(err))


@pytest.mark.parametrize("stage, signum", [("render", signal.SIGINT), ("simulate", signal.SIGINT),
                                           ("write", signal.SIGTERM), ("simulate", signal.SIGTERM)],
                         ids=["render-SIGINT", "simulate-SIGINT", "write-SIGTERM", "simulate-SIGTERM"])
def test_a_signal_at_any_stage_stops_in_one_line_and_the_rerun_resumes_to_the_same_bytes(tmp_path, reference,
                                                                                        stage, signum):
    out = tmp_path / "ds"
    p = stop_in(out, stage, signum)
    log = p.stdout + p.stderr
    word, code = ("interrupted", 130) if signum == signal.SIGINT else ("terminated", 143)
    assert p.returncode == code, log[-3000:]
    said = [x for x in p.stderr.splitlines() if x.startswith("factory:")]
    assert said == [STOPPED.format(word)], log[-3000:]
    assert "Traceback" not in log, log[-3000:]
    _only_the_first_sample(out)
    assert factory.run([*ARGS, "--out", str(out)]) == 0              # the same command resumes
    assert _files(out) == _files(reference) and _ids(out) == _ids(reference)
    assert list(out.rglob(".*")) == []


def _no_space(path) -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def test_a_full_disk_while_appending_the_manifest_line_leaves_the_sample_absent(tmp_path, reference, capsys,
                                                                               monkeypatch):
    """The second sample's line cannot be appended (half of it written, then
    ENOSPC): its files go, the manifest is cut back, one line says why."""
    from dcdi_core.errors import output_error
    real = commit.append_record

    def full(manifest, record):
        if record["id"] != SECOND:
            return real(manifest, record)
        with open(manifest, "a") as f:
            f.write(json.dumps(record)[:100])
        raise output_error(manifest, _no_space(manifest))
    monkeypatch.setattr(commit, "append_record", full)
    out = tmp_path / "ds"
    assert factory.run([*ARGS, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("factory: error: ") and "no space left" in err, err
    assert str(out / "manifest.jsonl") in err
    _only_the_first_sample(out)
    assert (out / "manifest.jsonl").read_text().endswith("}\n")          # cut back: no torn line
    monkeypatch.setattr(commit, "append_record", real)
    assert factory.run([*ARGS, "--out", str(out)]) == 0
    assert _files(out) == _files(reference)


def test_a_full_disk_while_writing_an_image_leaves_the_sample_absent(tmp_path, reference, capsys, monkeypatch):
    """ENOSPC while the second sample's aberrated image is written (its
    all-in-focus and depth already written): nothing of it is left."""
    from dcdi_core.atomic import atomic_path
    from dcdi_core.io import images
    real = images.write_image

    def full(path, image, **k):
        if SECOND in Path(path).name and Path(path).parent.name == "aberrated":
            with atomic_path(path) as tmp:
                Path(tmp).write_bytes(b"half an image")
                raise _no_space(tmp)
        return real(path, image, **k)
    monkeypatch.setattr(images, "write_image", full)
    out = tmp_path / "ds"
    assert factory.run([*ARGS, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no space left" in err and "aberrated" in err, err
    _only_the_first_sample(out)
    monkeypatch.setattr(images, "write_image", real)
    assert factory.run([*ARGS, "--out", str(out)]) == 0
    assert _files(out) == _files(reference)


def test_files_of_a_sample_without_a_manifest_line_are_removed_on_resume(tmp_path, reference, capsys):
    """A run killed between renaming a sample's files and appending its line
    (SIGKILL: nothing in the process can clean up) leaves the files; the
    next run removes them, even when it does not do that sample again."""
    import shutil
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    manifest = out / "manifest.jsonl"
    manifest.write_text(manifest.read_text().splitlines(keepends=True)[0])
    keep = out / "aif" / "notes.exr"                                     # not a sample's name: left alone
    keep.write_bytes(b"mine")
    capsys.readouterr()
    assert factory.run([*ARGS[:2], "--count", "1", *ARGS[4:], "--out", str(out)]) == 0
    assert "removed 5 file(s) of 1 sample(s) without a manifest line" in capsys.readouterr().out
    assert keep.read_bytes() == b"mine"
    keep.unlink()
    _only_the_first_sample(out)


def test_sample_folders_that_cannot_be_written_are_refused_before_any_render(tmp_path, capsys, monkeypatch):
    """aif/ is a file: refused in one line naming it, nothing rendered."""
    rendered = []
    monkeypatch.setattr(samples, "render_rgbd", lambda *a, **k: rendered.append(a))
    out = tmp_path / "ds"
    out.mkdir()
    (out / "aif").write_text("not a folder")
    assert factory.run([*ARGS, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(out / "aif") in err and "a file stands where a folder is needed" in err, err
    assert rendered == []


# ------------------------------------------------------------------ the mechanism, in-process
def test_a_stop_inside_deferred_waits_for_the_block_then_raises():
    done = []
    with signals.stop_on_signals():
        with pytest.raises(signals.Stopped) as e:
            with signals.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                done.append("the block ran to its end")
        assert signal.getsignal(signal.SIGTERM) is signals._raise      # the policy's handler is back
    assert done and e.value.exit_code == 143


def test_take_over_replaces_a_host_handler_and_leaves_pythons_default(monkeypatch):
    """Blender's SIGINT handler is installed outside Python (getsignal:
    None): taken with take_over, Python's default after the block; without
    it, left alone (the `dcdi` command)."""
    seen = []
    monkeypatch.setattr(signals.signal, "getsignal", lambda s: None)
    monkeypatch.setattr(signals.signal, "signal", lambda s, h: seen.append((s, h)))
    with signals.stop_on_signals():
        pass
    assert seen == []
    with signals.stop_on_signals(take_over=True):
        assert seen == [(signal.SIGINT, signals._raise), (signal.SIGTERM, signals._raise)]
    assert seen[2:] == [(signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)]


def test_a_render_blender_cancelled_is_a_stop_and_one_that_wrote_nothing_an_error(tmp_path, monkeypatch):
    """Blender's own Ctrl-C handler cancels a render and writes no file: a
    stop (exit 130), not 'file not found'; a finished render without its
    file: a RenderError naming it."""
    from types import SimpleNamespace

    from dcdi_core.errors import RenderError
    handlers = SimpleNamespace(render_cancel=[])

    def render(cancel: bool):
        def op(write_still):
            for f in handlers.render_cancel if cancel else []:
                f(None)
            return {"CANCELLED"} if cancel else {"FINISHED"}
        return op
    fake = SimpleNamespace(app=SimpleNamespace(handlers=handlers), ops=SimpleNamespace(render=None))
    monkeypatch.setitem(sys.modules, "bpy", fake)
    fake.ops.render = SimpleNamespace(render=render(True))
    with pytest.raises(signals.Stopped) as e:
        render_still(tmp_path / "r.exr")
    assert e.value.exit_code == 130 and handlers.render_cancel == []           # its handler removed
    fake.ops.render = SimpleNamespace(render=render(False))
    with pytest.raises(RenderError, match="r.exr: Blender finished the render but wrote no file"):
        render_still(tmp_path / "r.exr")
