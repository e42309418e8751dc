"""The dataset factory stopped in a real Blender binary (``blender
--background --python blender_addon/factory/batch.py``): Ctrl-C (SIGINT)
inside Blender's render and in the simulation, SIGTERM between a sample's
files. Blender has a SIGINT handler of its own, which cancelled the render
late and made the factory report its missing file (exit 2), and which
Python never heard of in the simulation (the Ctrl-C was lost). Each must
exit 130 / 143 with the one line, no traceback of ours, no temporary, the
first sample kept, and the same command resumes to the bytes of an
uninterrupted run. 24 x 32 pixels, two samples."""
from __future__ import annotations

import os
import signal
import subprocess
import threading
from pathlib import Path

import pytest

# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import blender, our_tracebacks  # noqa: E402,F401

ROOT = Path(__file__).resolve().parents[2]
PAUSE = ROOT / "tests" / "factory" / "stage_pause.py"
pytestmark = pytest.mark.realblender

ARGS = ["--recipe", "tabletop", "--count", "2", "--lens", "mos-s1", "--seed", "5", "--resolution", "24", "32",
        "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]
STOPPED = "factory: {}; the finished samples are kept: run the same command again to resume"


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("psf-cache")


def _command(blender: str, out: Path, pause: bool) -> list[str]:
    return [blender, "--background", "--factory-startup", "--python-exit-code", "1",
            *(["--python", str(PAUSE)] if pause else []),
            "--python", str(ROOT / "blender_addon" / "factory" / "batch.py"), "--", *ARGS, "--out", str(out)]


def _factory(blender: str, out: Path, cache: Path) -> subprocess.CompletedProcess:
    return subprocess.run(_command(blender, out, False), capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env=dict(os.environ, DCDI_CACHE_DIR=str(cache)))


@pytest.fixture(scope="module")
def reference(blender, cache, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "ds"
    p = _factory(blender, out, cache)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    return out


def blender_process(pid: int) -> int:
    """The Blender process itself: the deepest first descendant of ``pid``
    (a blender.org binary is ``pid``; the provisioned `blender` is a script
    that runs Blender under bwrap). A terminal's Ctrl-C reaches the whole
    foreground group, where that wrapper would die of it on its own: the
    status under test is Blender's, which bwrap and the script pass on."""
    kids = [int(k) for t in Path(f"/proc/{pid}/task").iterdir() for k in (t / "children").read_text().split()]
    return blender_process(kids[0]) if kids else pid


def stop_in(blender: str, out: Path, cache: Path, stage: str, signum: int) -> subprocess.CompletedProcess:
    """Run the factory, pausing 3 s in ``stage`` of its second sample; signal Blender 0.3 s into the pause."""
    env = dict(os.environ, DCDI_CACHE_DIR=str(cache), DCDI_TEST_STAGE_PAUSE=f"{stage} 2 3")
    p = subprocess.Popen(_command(blender, out, True), cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    stdout, err, timer = [], [], None
    reader = threading.Thread(target=lambda: stdout.extend(p.stdout), daemon=True)
    reader.start()
    for line in p.stderr:
        err.append(line)
        if line.startswith("stage pause:") and timer is None:
            timer = threading.Timer(0.3, lambda: os.kill(blender_process(p.pid), signum))
            timer.start()
    p.wait(timeout=300)
    reader.join(timeout=10)
    assert timer is not None, "".join(stdout + err)[-3000:]
    return subprocess.CompletedProcess(p.args, p.returncode, "".join(stdout), "".join(err))


def _files(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*.exr"))}


@pytest.mark.parametrize("stage, signum", [("render", signal.SIGINT), ("simulate", signal.SIGINT),
                                           ("write", signal.SIGTERM)],
                         ids=["render-SIGINT", "simulate-SIGINT", "write-SIGTERM"])
def test_the_factory_stops_at_any_stage_in_a_real_blender(blender, cache, reference, tmp_path, stage, signum):
    out = tmp_path / "ds"
    p = stop_in(blender, out, cache, stage, signum)
    log = p.stdout + p.stderr
    word, code = ("interrupted", 130) if signum == signal.SIGINT else ("terminated", 143)
    assert p.returncode == code, log[-3000:]
    said = [x for x in p.stderr.splitlines() if x.startswith("factory:") and not x.startswith("factory: warning:")]
    assert said == [STOPPED.format(word)], log[-3000:]
    assert not our_tracebacks(log) and "file not found" not in log, log[-3000:]
    assert len((out / "manifest.jsonl").read_text().splitlines()) == 1
    assert len(_files(out)) == 5 and list(out.rglob(".*")) == []            # the first sample, no temporary
    again = _factory(blender, out, cache)                                   # the same command resumes
    assert again.returncode == 0, (again.stdout + again.stderr)[-3000:]
    assert _files(out) == _files(reference)
