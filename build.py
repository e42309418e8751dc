#!/usr/bin/env python3
"""Set-up, test, demo and packaging entry point.

    python build.py demo [--out DIR]  # make .venv/, install, run the demo job: one factory sample,
                                      # then DCDI on it and on a synthetic scene, lens reports
    python build.py test              # make .venv/, install, run the fast test suite
    python build.py test-slow         # the tests marked slow, and the property-based ones at length
    python build.py test-blender      # the add-on and the factory in a real Blender binary (UI under
                                      # Xvfb, --background): $BLENDER, else `blender` on PATH, else one
                                      # provisioned by blender_addon/tools/real_blender.sh (Debian, root)
    python build.py bench ARGS        # `dcdi bench ARGS` inside the environment
    python build.py bench trace       # `dcdi bench trace`, beside Optiland 0.6.3 (its own venv
                                      # .venv-optiland/, made here once: it needs numpy 2)
    python build.py bench factory [--quick] [--recipe R]  # the dataset factory's samples per hour
    python build.py bench render [--quick]    # `dcdi bench render`, then the lens bokeh beside
                                              # Blender's Defocus node (time, memory, distance;
                                              # the lab's `python -m lab bench-defocus`)
    python build.py wheel             # the engine's wheel dist/dcdi-<version>-py3-none-any.whl
    python build.py addon             # the Blender extension zip dist/<id>-<version>.zip (with that wheel)

Works from any Python 3 interpreter: it finds a Python 3.11 (bpy 5.0.1 needs
it), makes the virtual environment `.venv/` beside this file and installs the
pinned dependencies once; later runs skip the install while requirements.txt
and pyproject.toml are unchanged (a stamp file records their hash).

The demo, the factory benchmark and the render benchmark's Defocus-node
row start the engine (`dcdi`) and the Blender batch jobs and tools
(blender_addon/factory/batch.py, lab/defocus_node.py) from here: the engine
never starts the Blender layer.

`wheel` builds the engine's package as a wheel (`pip wheel`, offline, with
every shipped data file: PSF bases, weights, lenses, the sensor response):
`dcdi_core` alone, without the add-on, the factory's scenes or the lab.
`addon` zips blender_addon/ (without its factory/ and tools/ folders of
batch jobs and developer tools) as the folder <id>/ with that wheel in
<id>/wheels/, listed by blender_addon/blender_manifest.toml (id, version):
Blender 4.2+ installs the zip from disk as an extension and its wheel with
it, offline; the add-on imports `dcdi_core` as an ordinary package. Same
sources, same bytes (fixed timestamps).
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
    for name in ("requirements.txt", "pyproject.toml", "setup.py"):
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


OPTILAND_VENV = ROOT / ".venv-optiland"
OPTILAND = "optiland==0.6.3"


def ensure_optiland() -> Path:
    """The python of `.venv-optiland/` (made with Optiland 0.6.3 when missing):
    the benchmark's other tracer, kept out of `.venv/` since it needs numpy 2."""
    py = OPTILAND_VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    if py.exists() and subprocess.run([py, "-c", "import optiland"], capture_output=True).returncode == 0:
        return py
    print(f"build.py: making {OPTILAND_VENV.name}/ with {OPTILAND} (once; a minute or two)", flush=True)
    if _run([find_python311(), "-m", "venv", "--clear", OPTILAND_VENV]) != 0 or \
            _run([py, "-m", "pip", "install", "-q", "--disable-pip-version-check", OPTILAND]) != 0:
        sys.exit(f"build.py: installing {OPTILAND} into {OPTILAND_VENV.name}/ failed (see pip's message above)")
    return py


def cmd_test(py: Path, marker: str, env: dict | None = None) -> int:
    code = _run([py, "-m", "pytest", "-m", marker, "-p", "no:cacheprovider"], env=env)
    if code == 5:
        print("build.py: pytest collected no tests: that is a failure, not a pass", flush=True)
        return 1
    return code


# ------------------------------------------------------------------ a real Blender for test-blender
MIN_REAL_BLENDER = (5, 0)
PROVISION = ROOT / "blender_addon" / "tools" / "real_blender.sh"


def blender_version(binary: str) -> tuple[int, int] | None:
    """(major, minor) that ``binary --version`` prints, or None when it does not run."""
    try:
        out = subprocess.run([binary, "--version"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    except (OSError, subprocess.TimeoutExpired):
        return None
    for line in out.stdout.splitlines():
        if line.startswith("Blender "):
            try:
                major, minor = line.split()[1].split(".")[:2]
                return int(major), int(minor)
            except ValueError:
                return None
    return None


def find_blender(provision: bool = True) -> str:
    """A Blender >= MIN_REAL_BLENDER binary: $BLENDER, else `blender` on PATH,
    else (as root on Debian/Ubuntu) one provisioned by real_blender.sh.
    Exits with what to do when there is none."""
    want = ".".join(map(str, MIN_REAL_BLENDER))
    given = os.environ.get("BLENDER")
    candidates = [given] if given else [shutil.which("blender") or ""]
    for cand in candidates:
        if not cand:
            continue
        v = blender_version(cand)
        if v is not None and v >= MIN_REAL_BLENDER:
            return cand
        why = "does not run" if v is None else f"is Blender {v[0]}.{v[1]}"
        if given:
            sys.exit(f"build.py: $BLENDER {given} {why}; test-blender needs Blender >= {want}")
        print(f"build.py: {cand} {why}; test-blender needs Blender >= {want}", flush=True)
    if not provision:
        sys.exit(f"build.py: no Blender >= {want} found: set $BLENDER to one, or run {PROVISION.relative_to(ROOT)} "
                 "provision as root (Debian/Ubuntu)")
    print(f"build.py: no Blender >= {want} found; provisioning one ({PROVISION.relative_to(ROOT)} provision, "
          "about 5 minutes)", flush=True)
    if _run(["bash", PROVISION, "provision"]) != 0:
        sys.exit("build.py: provisioning a Blender failed (see above); set $BLENDER to a Blender >= "
                 f"{want} binary instead")
    return find_blender(provision=False)


def cmd_test_blender(py: Path, rest: list[str]) -> int:
    """The real-Blender suite (tests/blender, marker realblender) with $BLENDER
    set to the Blender found; needs xvfb-run for the UI tests."""
    blender = find_blender()
    if shutil.which("xvfb-run") is None:
        sys.exit("build.py: test-blender needs xvfb-run for the UI (apt-get install xvfb xauth)")
    print(f"build.py: testing in {blender} ({'.'.join(map(str, blender_version(blender)))})", flush=True)
    build_addon()
    env = dict(os.environ, BLENDER=blender)
    code = _run([py, "-m", "pytest", "-m", "realblender", "-p", "no:cacheprovider", "tests/blender", *rest], env=env)
    if code == 5:
        print("build.py: pytest collected no real-Blender tests: that is a failure, not a pass", flush=True)
        return 1
    return code


# folders of blender_addon/ left out of the zip: the dataset factory (a batch
# job that needs the repository's scenes/ and runs under `blender --background`)
# and the developer tools (screenshots, studies)
ADDON_EXCLUDE_DIRS = ("factory", "tools")
# what the wheel is built from (a copy: the build's own folders stay out of the checkout)
WHEEL_SOURCES = ("pyproject.toml", "setup.py", "README.md", "dcdi_core", "lenses")
# fixed timestamps inside the wheel (setuptools reads it): same sources, same bytes
SOURCE_DATE_EPOCH = "315532800"


def _package_version() -> str:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def wheel_name() -> str:
    """The file name of the engine's wheel (pure Python: any platform, Blender's Python too)."""
    return f"dcdi-{_package_version()}-py3-none-any.whl"


def build_wheel(out_dir: Path, python: str | Path | None = None) -> Path:
    """``pip wheel`` of the package (with every shipped data file: PSF
    bases, weights, lenses, the sensor response) into ``out_dir``, from a
    copy of its sources, offline (no build isolation: the setuptools of
    ``python``, default the set-up's); returns its path."""
    import tempfile
    # the set-up's Python has setuptools and wheel; build.py may run under another
    python = str(python or (_venv_python() if _venv_python().exists() else sys.executable))
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="dcdi-wheel-") as tmp:
        src = Path(tmp) / "src"
        for name in WHEEL_SOURCES:
            p = ROOT / name
            if p.is_dir():
                shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info"))
            else:
                src.mkdir(exist_ok=True)
                shutil.copyfile(p, src / name)
        env = dict(os.environ, SOURCE_DATE_EPOCH=SOURCE_DATE_EPOCH, PIP_DISABLE_PIP_VERSION_CHECK="1")
        r = subprocess.run([python, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                            "-q", "-w", str(Path(tmp) / "wheel"), str(src)], env=env, capture_output=True, text=True)
        built = Path(tmp) / "wheel" / wheel_name()
        if r.returncode != 0 or not built.is_file():
            sys.exit(f"build.py: building the wheel failed ({python} -m pip wheel):\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
        out = out_dir / built.name
        shutil.copyfile(built, out)
    return out


def _addon_files() -> list[tuple[Path, str]]:
    """(source, name inside the package folder) of the add-on's own files."""
    addon = ROOT / "blender_addon"
    return [(p, p.relative_to(addon).as_posix()) for p in sorted(addon.rglob("*"))
            if p.is_file() and "__pycache__" not in p.parts and p.relative_to(addon).parts[0] not in ADDON_EXCLUDE_DIRS
            and p.suffix in (".py", ".toml", ".md")]


def _manifest_wheels(manifest: dict) -> list[str]:
    wheels = manifest.get("wheels", [])
    if wheels != [f"./wheels/{wheel_name()}"]:
        sys.exit(f"build.py: blender_manifest.toml wheels = {wheels!r}; it must list the engine's wheel, "
                 f"[\"./wheels/{wheel_name()}\"] (pyproject.toml's version)")
    return wheels


def build_addon(out_dir: Path = ROOT / "dist", python: str | Path | None = None) -> Path:
    """Write dist/<id>-<version>.zip (temporary name, then renamed): the
    add-on's package folder <id>/ with the engine's wheel in <id>/wheels/, as
    its manifest lists it (Blender 4.2+ installs the wheel with the
    extension, offline). Returns its path."""
    import tempfile
    manifest = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())
    ext_id, version = manifest["id"], manifest["version"]
    if not ext_id.isidentifier():
        sys.exit(f"build.py: blender_manifest.toml id {ext_id!r} must be a Python identifier")
    wheels = _manifest_wheels(manifest)
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{ext_id}-{version}.zip"
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        with tempfile.TemporaryDirectory(prefix="dcdi-addon-") as wdir:
            wheel = build_wheel(Path(wdir), python)
            files = _addon_files() + [(wheel, wheels[0].removeprefix("./"))]
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
                for src, name in files:
                    info = zipfile.ZipInfo(f"{ext_id}/{name}", date_time=(1980, 1, 1, 0, 0, 0))
                    # a wheel is a zip already: stored, not deflated again
                    info.compress_type = zipfile.ZIP_STORED if name.endswith(".whl") else zipfile.ZIP_DEFLATED
                    info.external_attr = 0o644 << 16
                    z.writestr(info, src.read_bytes())
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


# ------------------------------------------------------------------ demo and benchmark of the factory
def _option(argv: list[str], name: str, default: str) -> str:
    return argv[argv.index(name) + 1] if name in argv[:-1] else default


# the networks' training frames span the sensor at 480 x 640: the factory's
# camera does too at this resolution, so the sample is at their pixel pitch
FACTORY_DEMO_RESOLUTION = (480, 640)


def factory_demo(py: Path, out: Path) -> int:
    """The demo job: one dataset-factory sample (room recipe, Blender Cycles,
    MOS-S1) in OUT/factory-480x640/ (a finished one is kept: the factory
    resumes), then the engine's demo (`python -m dcdi_core.demo`) with that
    sample as its second scene, or with the reason there is none (the
    engine's demo then runs on its synthetic scene alone). Output lines of
    the factory go to OUT/factory.log; its progress lines are shown too."""
    import time

    h, w = FACTORY_DEMO_RESOLUTION
    # the resolution in the name: a folder of other settings is never resumed (the factory refuses it)
    folder, log = out / f"factory-{h}x{w}", out / "factory.log"
    print(f"factory: one room sample at {h} x {w} (Blender Cycles; MOS-S1) in {folder}", flush=True)
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    code = _factory_sample(py, folder, log, h, w)
    if code == 2 and "Rerun with the folder's settings" in log.read_text(errors="replace"):
        # the demo's own sample, made by an older factory (its scenes or settings changed): make it anew
        print(f"  factory: {folder} holds a sample of other settings; making it anew", flush=True)
        shutil.rmtree(folder)
        code = _factory_sample(py, folder, log, h, w)
    args = [str(py), "-m", "dcdi_core.demo", "--out", str(out)]
    if code == 0:
        print(f"  factory: done in {time.perf_counter() - t0:.1f} s (its log: {log})", flush=True)
        args += ["--factory-sample", str(folder)]
    else:
        lines = [x.strip() for x in log.read_text(errors="replace").splitlines() if x.strip()]
        why = f"the factory sample failed (exit {code}: {lines[-1] if lines else 'no output'}; its log: {log})"
        print(f"  {why}; the demo goes on with the synthetic scene alone", flush=True)
        args += ["--factory-error", why]
    return _run(args)


def _factory_sample(py: Path, folder: Path, log: Path, h: int, w: int) -> int:
    """Run the factory for the demo's one room sample; its output to ``log``,
    its progress lines shown. Returns its exit status."""
    with open(log, "w") as f, subprocess.Popen(
            [str(py), "-m", "blender_addon.factory", "--recipe", "room", "--count", "1", "--lens", "mos-s1",
             "--out", str(folder), "--seed", "0", "--resolution", str(h), str(w)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace") as job:
        for line in job.stdout:
            f.write(line)
            # the factory's own progress; Blender's timestamped log lines stay in the log
            if line.strip() and not line[:1].isdigit():
                print("  " + line.strip(), flush=True)
    return job.returncode


def bench_factory(py: Path, quick: bool = False, recipes=("room", "leaves")) -> int:
    """Samples per hour of the dataset factory at 480 x 640 (default render
    settings, MOS-S1 simulation included), per recipe, with the time of each
    stage from its manifest (seconds per sample). A Blender recipe runs one
    process (Cycles keeps every core busy); the numpy recipe runs one shard
    per core, as a user fills a machine with it. The PSF library is built
    (or read) by a warm-up run before the timed one; the timed run's wall
    time includes its process start. CPU seconds and the load average show
    whether other jobs shared the machine (wall times then grow)."""
    for recipe in recipes:
        code = _bench_factory_recipe(py, recipe, quick)
        if code:
            return code
    return 0


def _bench_factory_recipe(py: Path, recipe: str, quick: bool) -> int:
    import json
    import math
    import tempfile
    import time

    ncpu = os.cpu_count() or 1
    blender = recipe != "leaves"
    shards = 1 if blender else ncpu
    h, w = (120, 160) if quick else (480, 640)
    n = (2 if quick else 6) if blender else (8 if quick else 40) * shards
    with tempfile.TemporaryDirectory() as d:
        def args(shard: int, folder: str):
            return [str(py), "-m", "blender_addon.factory", "--recipe", recipe, "--lens", "mos-s1", "--out", folder,
                    "--seed", "0", "--resolution", str(h), str(w), "--shard", f"{shard}/{shards}"]
        # one warm-up sample builds (or reads) the PSF library for this pixel pitch
        subprocess.run(args(0, os.path.join(d, "warm")) + ["--count", "1"], check=True, capture_output=True,
                       cwd=ROOT)
        folders = [os.path.join(d, f"shard{i}") for i in range(shards)]
        load0 = os.getloadavg()[0]
        t = time.perf_counter()
        procs = [subprocess.Popen(args(i, f) + ["--count", str(n)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, cwd=ROOT) for i, f in enumerate(folders)]
        for p in procs:
            _, err = p.communicate()
            if p.returncode:
                print(err.decode(errors="replace"), file=sys.stderr)
                return p.returncode
        wall = time.perf_counter() - t
        load1 = os.getloadavg()[0]
        recs = []
        for f in folders:
            with open(os.path.join(f, "manifest.jsonl")) as fh:
                recs += [json.loads(x) for x in fh if x.strip()]

    def mean(f):
        return sum(f(r) for r in recs) / len(recs)
    stages = ("scene", "render", "read", "write", "simulate")
    st = {k: mean(lambda r, k=k: r["stage_seconds"].get(k, 0.0)) for k in stages}
    steady = mean(lambda r: r["seconds"] - r["stage_seconds"].get("setup", 0.0))
    cpu = mean(lambda r: r["cpu_seconds"])
    per = wall / len(recs)
    r0 = recs[0]["render"]
    how = (f"Cycles {r0['samples']} samples/pixel, denoiser "
           f"{r0['denoising_quality'] if r0['denoise'] else 'off'}/{r0['denoising_prefilter']}" if blender
           else f"numpy, {shards} shard processes")
    print(f"bench factory: {recipe}, {h} x {w}, {how}, MOS-S1 simulation (depth-aware + baseline), "
          f"{len(recs)} samples, {ncpu} CPU(s), load average {load0:.1f} -> {load1:.1f}")
    cst = {k: mean(lambda r, k=k: r["stage_seconds"].get("cpu_" + k, math.nan)) for k in stages}
    print("  per sample, wall (CPU) seconds: "
          + ", ".join(f"{k} {v:.2f}" + ("" if math.isnan(cst[k]) else f" ({cst[k]:.2f})") for k, v in st.items())
          + f"; {steady:.2f} s in all, {cpu:.2f} CPU s")
    goal = 600 if blender else 6000
    print(f"  {wall:.1f} s for {len(recs)} samples with the process start = {3600 / per:.0f} samples per hour "
          f"on {ncpu} cores (goal {goal})")
    if load0 > 1.5 * ncpu / 2 or load1 > ncpu + 0.5:
        print(f"  note: other jobs shared the {ncpu} cores (load average {load0:.1f} -> {load1:.1f}): "
              "wall times are longer than on an idle machine; CPU seconds are not")
    return 0


def bench_defocus(py: Path, quick: bool = False) -> int:
    """Below `dcdi bench render`: the 6P lens bokeh (dcdi_core, occlusion-aware
    and plain) beside Blender's compositor Defocus node on the same RGB-D,
    each timed and scored against a per-pixel reference of the real lens
    (`python -m lab bench-defocus`); the node runs in its own process under pip
    bpy (lab/defocus_node.py), which reports its times and
    its peak RSS; the process's whole wall time (Blender's start-up
    included) is measured here."""
    import json
    import tempfile
    import time

    with tempfile.TemporaryDirectory() as d:
        code = subprocess.call([str(py), "-m", "lab", "bench-defocus", "engine", "--out", d]
                               + (["--quick"] if quick else []), cwd=ROOT)
        if code != 0:
            return code
        args = json.loads(Path(d, "engine.json").read_text())["node_args"]
        t = time.perf_counter()
        node = subprocess.run([str(py), "-m", "lab.defocus_node", "--input", str(Path(d, "rgbd.npz")),
                               *args, "--out", str(Path(d, "node.npz")), "--json", str(Path(d, "node.json")),
                               "--repeat", "1" if quick else "2"], cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if node.returncode != 0:
            print(node.stdout + node.stderr, end="")
            print(f"  the Defocus node failed (exit {node.returncode}): run `python -m "
                  "lab.defocus_node ...` to see why")
            return node.returncode
        return subprocess.call([str(py), "-m", "lab", "bench-defocus", "score", "--out", d,
                                "--node-process-s", f"{wall:.3f}"], cwd=ROOT)


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in ("demo", "test", "test-slow", "test-blender", "bench", "setup", "addon", "wheel"):
        print(__doc__)
        print(f"build.py: unknown command {command!r}")
        return 2
    py = ensure_environment()
    if command == "setup":
        return 0
    if command in ("addon", "wheel"):
        out = build_addon(python=py) if command == "addon" else build_wheel(ROOT / "dist", py)
        print(f"build.py: wrote {out.relative_to(ROOT)} ({out.stat().st_size / 1e6:.2f} MB)")
        return 0
    if command == "test":
        return cmd_test(py, "not slow and not realblender")
    if command == "test-slow":
        # the slow tests, and the property-based ones again with many examples
        return cmd_test(py, "(slow or property) and not realblender", env=dict(os.environ, DCDI_HYPOTHESIS_PROFILE="long"))
    if command == "test-blender":
        return cmd_test_blender(py, rest)
    if command == "bench":
        if rest[:1] == ["factory"]:
            picked = [rest[i + 1] for i, x in enumerate(rest[:-1]) if x == "--recipe"]
            return bench_factory(py, quick="--quick" in rest, recipes=picked or ("room", "leaves"))
        if rest[:1] == ["trace"] and "--optiland" not in rest:
            rest = [*rest, "--optiland", str(ensure_optiland())]
        code = _run([py, "-m", "dcdi_core", "bench", *rest])
        if code != 0 or rest[:1] != ["render"]:
            return code
        return bench_defocus(py, quick="--quick" in rest)
    return factory_demo(py, (ROOT / _option(rest, "--out", "out/demo")).resolve())


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
