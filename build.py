#!/usr/bin/env python3
"""Set-up, test, demo and packaging entry point.

    python build.py demo        # make .venv/, install, run the demo job
    python build.py test        # make .venv/, install, run the fast test suite
    python build.py test-slow   # the tests marked slow
    python build.py bench ARGS  # `dcdi bench ARGS` inside the environment
    python build.py addon       # the Blender extension zip dist/<id>-<version>.zip

Works from any Python 3 interpreter: it finds a Python 3.11 (bpy 5.0.1 needs
it), makes the virtual environment `.venv/` beside this file and installs the
pinned dependencies once; later runs skip the install while requirements.txt
and pyproject.toml are unchanged (a stamp file records their hash).

`addon` needs no environment: it zips blender_addon/ (without the batch
tools) as the folder <id>/ with dcdi_core/ and lenses/ vendored inside it,
id and version from blender_addon/blender_manifest.toml. The zip installs as
an extension in Blender 4.2+ (Install from Disk) and as a legacy add-on in
older Blender (its bl_info). Same sources, same bytes (fixed timestamps).
"""
from __future__ import annotations

import glob
import hashlib
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
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


# batch tools that need the repository (scenes/, OpenImageIO): not part of the add-on
ADDON_EXCLUDE = {"factory.py", "render_noise.py", "screenshots.py"}


def _addon_files() -> list[tuple[Path, str]]:
    """(source, name inside the package folder) of every file in the add-on."""
    def tree(folder: Path, prefix: str, keep) -> list[tuple[Path, str]]:
        return [(p, prefix + p.relative_to(folder).as_posix()) for p in sorted(folder.rglob("*"))
                if p.is_file() and "__pycache__" not in p.parts and keep(p)]
    files = tree(ROOT / "blender_addon", "", lambda p: p.parent == ROOT / "blender_addon"
                 and p.name not in ADDON_EXCLUDE and p.suffix in (".py", ".toml", ".md"))
    files += tree(ROOT / "dcdi_core", "dcdi_core/", lambda p: p.suffix in (".py", ".csv", ".md", ".json"))
    files += tree(ROOT / "lenses", "lenses/", lambda p: p.suffix in (".toml", ".md"))
    return files


def build_addon(out_dir: Path = ROOT / "dist") -> Path:
    """Write dist/<id>-<version>.zip (temporary name, then renamed); returns its path."""
    manifest = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())
    ext_id, version = manifest["id"], manifest["version"]
    if not ext_id.isidentifier():
        sys.exit(f"build.py: blender_manifest.toml id {ext_id!r} must be a Python identifier")
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{ext_id}-{version}.zip"
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
            for src, name in _addon_files():
                info = zipfile.ZipInfo(f"{ext_id}/{name}", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                z.writestr(info, src.read_bytes())
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command == "addon":
        out = build_addon()
        print(f"build.py: wrote {out.relative_to(ROOT)} ({out.stat().st_size / 1e6:.2f} MB)")
        return 0
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
