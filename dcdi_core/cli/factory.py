"""`dcdi-factory`: the dataset factory as a command, from any folder.

The factory is a batch job of Blender (its scenes in the repository's
``scenes/``, its Blender code in ``blender_addon/factory/``), not part of
the engine's wheel. A dataset builder clones the repository and installs it
editable (``pip install -e CLONE``, or ``python build.py test``, which does
it in ``.venv/``); this command then finds the clone through the installed
engine and runs the factory there, as a separate process, with the
arguments given (``python -m blender_addon.factory --help`` lists them):

    dcdi-factory --recipe room --count 100 --lens mos-s1 --out DIR --seed 0
    dcdi-factory --blender /path/to/blender --recipe room ...   # in that Blender, --background
    dcdi-factory merge SHARD_DIR... --count N --out DIR

``--blender PATH`` runs it in a Blender binary (``blender --background
--python blender_addon/factory/batch.py -- ...``) instead of this Python
(which then needs the pip ``bpy``, except for ``--recipe leaves`` and
``merge``); ``--checkout DIR`` (or ``DCDI_CHECKOUT``) names the clone where
the engine was installed from a wheel. Relative paths are the caller's: the
factory runs in the folder the command was started from. Its exit status
and its one-line errors are the factory's; Ctrl-C and SIGTERM reach it and
it stops as it does on its own (the finished samples kept).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

USAGE = ("usage: dcdi-factory [--blender PATH] [--checkout DIR] FACTORY_ARGS...  "
         "(the dataset factory from any folder; FACTORY_ARGS: dcdi-factory --help)")


class NoCheckout(Exception):
    """No clone of the repository holds the factory."""


def _holds_factory(root: Path) -> bool:
    return (root / "blender_addon" / "factory" / "batch.py").is_file() and (root / "scenes" / "recipes.py").is_file()


def checkout(given: str | None = None) -> Path:
    """The clone that holds the factory: ``given`` (``--checkout``), else
    ``$DCDI_CHECKOUT``, else the folder the engine was installed from (an
    editable install's, or a checkout run in place)."""
    named = given or os.environ.get("DCDI_CHECKOUT")
    if named:
        root = Path(named).expanduser().resolve()
        if not _holds_factory(root):
            origin = "--checkout" if given else "DCDI_CHECKOUT"
            raise NoCheckout(f"{origin} {root}: no dataset factory there (blender_addon/factory/batch.py and "
                             "scenes/recipes.py): give the folder of a clone of the repository")
        return root
    root = Path(__file__).resolve().parents[2]
    if _holds_factory(root):
        return root
    raise NoCheckout("the dataset factory runs from a clone of the repository (its scenes and Blender code are "
                     "not in the engine's wheel): clone it and `pip install -e CLONE`, or give --checkout CLONE "
                     "(or set DCDI_CHECKOUT)")


def _split(argv: list[str]) -> tuple[str | None, str | None, list[str]]:
    """(--blender, --checkout, the factory's own arguments)."""
    blender = given = None
    rest, i = [], 0
    while i < len(argv):
        a = argv[i]
        for name in ("--blender", "--checkout"):
            if a == name or a.startswith(name + "="):
                if a == name:
                    if i + 1 >= len(argv):
                        raise NoCheckout(f"{name} needs a value ({'a Blender binary' if name == '--blender' else 'a folder'})")
                    value, i = argv[i + 1], i + 1
                else:
                    value = a.split("=", 1)[1]
                blender, given = (value, given) if name == "--blender" else (blender, value)
                break
        else:
            rest.append(a)
        i += 1
    return blender, given, rest


def command(argv: list[str]) -> tuple[list[str], dict]:
    """(the factory's command line, its environment) for ``argv``."""
    blender, given, rest = _split(argv)
    root = checkout(given)
    env = dict(os.environ)
    if blender is not None:
        if not (Path(blender).is_file() and os.access(blender, os.X_OK)):
            raise NoCheckout(f"--blender {blender}: not an executable file (give the Blender binary)")
        return [blender, "--background", "--factory-startup", "--python-exit-code", "1",
                "--python", str(root / "blender_addon" / "factory" / "batch.py"), "--", *rest], env
    env["PYTHONPATH"] = os.pathsep.join([str(root)] + [p for p in [env.get("PYTHONPATH")] if p])
    return [sys.executable, "-m", "blender_addon.factory", *rest], env


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] in (["-h"], ["--help"]):
        print(USAGE)
    try:
        cmd, env = command(argv)
    except NoCheckout as e:
        print(f"dcdi-factory: error: {e}", file=sys.stderr)
        return 2
    child = subprocess.Popen(cmd, env=env)
    # SIGTERM (a timeout, a job runner) is the factory's to answer: passed on; Ctrl-C reaches it as it
    # reaches this process (one process group), and this one waits for its answer
    previous = signal.signal(signal.SIGTERM, lambda *_: child.send_signal(signal.SIGTERM))
    try:
        while True:
            try:
                return child.wait()
            except KeyboardInterrupt:
                continue
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
