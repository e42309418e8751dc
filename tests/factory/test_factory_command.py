"""`dcdi-factory`, the dataset factory as an installed command: run from a
folder outside the clone, it finds the clone through the installed engine
(an editable install), runs the factory with the caller's relative paths,
and says in one line what is missing where no clone holds the factory."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dcdi_core.cli import factory as launcher

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--resolution", "24", "32", "--psf-rays", "12", "--psf-wavelengths", "3"]


def _command() -> list[str]:
    """The installed entry point beside this Python (build.py installs the project editable in .venv/)."""
    script = Path(sys.executable).with_name("dcdi-factory")
    if not script.exists():
        pytest.fail(f"no {script}: the project's entry points are not installed (rerun `python build.py test`)")
    return [str(script)]


def test_the_installed_command_runs_the_factory_from_any_folder(tmp_path):
    away = tmp_path / "elsewhere"
    away.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DCDI_CHECKOUT")}
    p = subprocess.run([*_command(), "--recipe", "leaves", "--count", "1", "--lens", "mos-s1", "--out", "ds",
                        "--seed", "0", *SMALL], cwd=away, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    records = [json.loads(x) for x in (away / "ds" / "manifest.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == ["leaves-000000"]
    assert (away / "ds" / "mos-s1" / "aberrated" / "leaves-000000.exr").exists()
    # the factory's own errors come back as they are: one line, its exit status
    p = subprocess.run([*_command(), "--recipe", "kitchen", "--count", "1", "--out", "x"], cwd=away, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stderr.strip().startswith("factory: error:") and "'kitchen'" in p.stderr
    assert not (away / "x").exists()


@pytest.mark.parametrize("argv, words", [
    (["--checkout", "{empty}", "--recipe", "leaves"], "--checkout {empty}: no dataset factory there"),
    (["--blender", "{empty}/blender", "--recipe", "leaves"], "--blender {empty}/blender: not an executable file"),
    (["--recipe", "leaves", "--checkout"], "--checkout needs a value"),
])
def test_what_the_command_cannot_find_it_says_in_one_line(tmp_path, capsys, argv, words):
    empty = tmp_path / "empty"
    empty.mkdir()
    argv = [a.format(empty=empty) for a in argv]
    assert launcher.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("dcdi-factory: error: ") and words.format(empty=empty) in err


def test_an_engine_installed_from_the_wheel_is_told_where_the_factory_is(monkeypatch, tmp_path):
    monkeypatch.delenv("DCDI_CHECKOUT", raising=False)
    monkeypatch.setattr(launcher, "__file__", str(tmp_path / "site-packages" / "dcdi_core" / "cli" / "factory.py"))
    with pytest.raises(launcher.NoCheckout, match=r"clone it and `pip install -e CLONE`, or give --checkout"):
        launcher.checkout()
    monkeypatch.setenv("DCDI_CHECKOUT", str(ROOT))
    assert launcher.checkout() == ROOT
    cmd, env = launcher.command(["--recipe", "leaves"])
    assert cmd[1:] == ["-m", "blender_addon.factory", "--recipe", "leaves"]
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(ROOT)
