#!/usr/bin/env python3
"""Set-up, test, demo and packaging entry point.

    python build.py demo        # make .venv/, install, run the demo job
    python build.py test        # make .venv/, install, run the fast test suite
    python build.py test-slow   # the tests marked slow
    python build.py bench ARGS  # `dcdi bench ARGS` inside the environment

Works from any Python 3 interpreter: it finds a Python 3.11 (bpy 5.0.1 needs
it), makes the virtual environment `.venv/` beside this file and installs the
pinned dependencies once; later runs skip the install while requirements.txt
and pyproject.toml are unchanged (a stamp file records their hash).
"""
from __future__ import annotations

import glob
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".dcdi-setup-stamp"
WANTED = (3, 11)


def _venv_python() -> Path:
    return VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def _version_of(python: str) -> tuple[int, int] | None:
    try:
        out = subprocess.run([python, "-c", "import sys; print(*sys.version_info[:2])"],
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    major, minor = out.stdout.split()
    return int(major), int(minor)


def find_python311() -> str:
    """Path of a Python 3.11 interpreter, even when `python` is another version."""
    candidates = []
    if sys.version_info[:2] == WANTED:
        candidates.append(sys.executable)
    candidates += [shutil.which("python3.11") or "", shutil.which("python3") or ""]
    home = Path.home()
    candidates += sorted(glob.glob(str(home / ".pyenv/versions/3.11*/bin/python3.11")), reverse=True)
    candidates += ["/usr/bin/python3.11", "/usr/local/bin/python3.11",
                   "/opt/homebrew/bin/python3.11", "/usr/local/opt/python@3.11/bin/python3.11"]
    if os.name == "nt" and shutil.which("py"):
        out = subprocess.run(["py", "-3.11", "-c", "import sys; print(sys.executable)"],
                             capture_output=True, text=True)
        if out.returncode == 0:
            candidates.append(out.stdout.strip())
    for cand in candidates:
        if cand and Path(cand).exists() and _version_of(cand) == WANTED:
            return cand
    sys.exit("build.py: no Python 3.11 found (bpy 5.0.1 needs exactly 3.11). "
             "Install it (e.g. `pyenv install 3.11`, or your system's python3.11 package) and rerun.")


def _setup_hash() -> str:
    h = hashlib.sha256()
    for name in ("requirements.txt", "pyproject.toml"):
        h.update((ROOT / name).read_bytes())
    return h.hexdigest()


def _run(cmd: list[str], **kw) -> int:
    print("+", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.call([str(c) for c in cmd], cwd=ROOT, **kw)


def ensure_environment() -> Path:
    """Create `.venv/` and install the pinned dependencies unless already done."""
    py = _venv_python()
    if py.exists() and _version_of(str(py)) != WANTED:
        print(f"build.py: {VENV} is not Python 3.11; recreating it", flush=True)
        shutil.rmtree(VENV)
    if not py.exists():
        base = find_python311()
        if _run([base, "-m", "venv", VENV]) != 0:
            sys.exit("build.py: could not create the virtual environment .venv/")
    wanted = _setup_hash()
    if STAMP.exists() and STAMP.read_text().strip() == wanted:
        return py
    steps = [
        [py, "-m", "pip", "install", "--disable-pip-version-check", "-r", ROOT / "requirements.txt"],
        [py, "-m", "pip", "install", "--disable-pip-version-check", "--no-deps",
         "--no-build-isolation", "-e", ROOT],
    ]
    for step in steps:
        if _run(step) != 0:
            sys.exit("build.py: installing dependencies failed (see pip's message above)")
    tmp = STAMP.with_suffix(".tmp")
    tmp.write_text(wanted + "\n")
    os.replace(tmp, STAMP)
    return py


def cmd_test(py: Path, marker: str) -> int:
    code = _run([py, "-m", "pytest", "-m", marker, "-p", "no:cacheprovider"])
    if code == 5:
        print("build.py: pytest collected no tests: that is a failure, not a pass", flush=True)
        return 1
    return code


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in ("demo", "test", "test-slow", "bench", "setup"):
        print(__doc__)
        print(f"build.py: unknown command {command!r}")
        return 2
    py = ensure_environment()
    if command == "setup":
        return 0
    if command == "test":
        return cmd_test(py, "not slow")
    if command == "test-slow":
        return cmd_test(py, "slow")
    if command == "bench":
        return _run([py, "-m", "dcdi_core", "bench", *rest])
    return _run([py, "-m", "dcdi_core", "demo", *rest])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
