"""The repository's build.py as a module (it is a script, not a package):
what the tests use to build the wheel and the add-on zip."""
import importlib.util
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


@lru_cache(maxsize=1)
def build_module():
    spec = importlib.util.spec_from_file_location("dcdi_build", ROOT / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
