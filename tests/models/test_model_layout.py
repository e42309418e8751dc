"""The layout's one-way rules, read from the source (imports, not mentions;
imports inside functions count; relative imports resolved):

- ``dcdi_core.models.runtime`` (what the Blender add-on bundles, numpy only)
  imports neither torch nor the training code (``models.olf``, ``.dacn``,
  ``.depth``, ``.common``);
- nothing in ``dcdi_core`` outside ``experiments`` imports
  ``dcdi_core.experiments`` (the reports use the engine, never the reverse),
  except the command line, whose ``dcdi report`` and ``dcdi bench`` run them;
- ``dcdi_core`` never imports ``blender_addon`` or Blender's own modules
  (a bench may start Blender as another process: that is no import).
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENGINE = ROOT / "dcdi_core"

RUNTIME_MAY_NOT = ("torch", "dcdi_core.models.olf", "dcdi_core.models.dacn", "dcdi_core.models.depth",
                   "dcdi_core.models.common")
BLENDER = ("blender_addon", "bpy", "bmesh")
# the door to the reports: `dcdi report` and `dcdi bench` import them
MAY_IMPORT_EXPERIMENTS = ("dcdi_core/cli.py", "dcdi_core/cli/")


def module_name(path: Path, root: Path) -> tuple[str, bool]:
    """(dotted name of the module at ``path`` below ``root``, whether it is a package's __init__)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    package = parts[-1] == "__init__"
    if package:
        parts = parts[:-1]
    return ".".join(parts), package


def imported(source: str, module: str, is_package: bool = False) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of everything ``source`` (the module
    ``module``) imports, anywhere in it; ``from a import b`` gives ``a`` and
    ``a.b`` (b may be a submodule), relative imports resolved against
    ``module``; ``importlib.import_module("x")`` and ``__import__("x")``
    with a literal name count too."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            head = ".".join(base + ([node.module] if node.module else []))
            out.append((node.lineno, head))
            out += [(node.lineno, f"{head}.{a.name}") for a in node.names if a.name != "*"]
        elif isinstance(node, ast.Call) and _dynamic_import(node):
            out.append((node.lineno, node.args[0].value))
    return out


def _dynamic_import(node: ast.Call) -> bool:
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    return (name in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str))


def _within(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def violations(root: Path) -> list[str]:
    """Every import in the ``dcdi_core`` below ``root`` that breaks a rule of
    the module docstring, as 'file:line: imports name (rule)'."""
    out = []
    for path in sorted((root / "dcdi_core").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        module, is_package = module_name(path, root)
        for line, name in imported(path.read_text(encoding="utf-8"), module, is_package):
            where = f"{rel}:{line}: imports {name}"
            if rel.startswith("dcdi_core/models/runtime/") and _within(name, RUNTIME_MAY_NOT):
                out.append(where + " (the runtime is numpy only, without training code)")
            if (_within(name, ("dcdi_core.experiments",)) and not rel.startswith("dcdi_core/experiments/")
                    and not rel.startswith(MAY_IMPORT_EXPERIMENTS)):
                out.append(where + " (the engine never uses the experiments)")
            if _within(name, BLENDER):
                out.append(where + " (dcdi_core never imports Blender or the add-on)")
            if rel.startswith(("dcdi_core/render/", "dcdi_core/correct/")) and _within(name, ("dcdi_core.models",)):
                out.append(where + " (render and correct never import the networks: a PSF source is handed in)")
            if rel.startswith("dcdi_core/correct/") and _within(name, ("torch",)):
                out.append(where + " (the deconvolution is numpy only: it runs in Blender)")
    return out


def test_the_tree_keeps_the_layouts_rules():
    assert violations(ROOT) == []


def test_the_checker_finds_each_kind_of_import(tmp_path):
    """A bad import of each form is found; mentions are not imports."""
    files = {
        "dcdi_core/models/runtime/bad.py": (
            '"""import torch is only mentioned here"""\n'
            "import numpy as np\n"
            "from ...psf import library\n"                 # allowed: the engine's numpy code
            "from ..registry import NETWORKS\n"
            "def f():\n"
            "    import torch.nn\n"                         # function-local
            "    from ..olf import arch\n"                  # relative, to the training code
            "    from .. import common\n"                   # a subpackage by name
            "    return importlib.import_module('dcdi_core.models.dacn.train')\n"),
        "dcdi_core/models/runtime/__init__.py": "from ..depth.arch import DepthNet\n",
        "dcdi_core/render/x.py": "def g():\n    from ..experiments import bench\n    import bpy\n",
        "dcdi_core/correct/y.py": "from ..models.runtime.library import psf_source\n",
        "dcdi_core/cli/reports.py": "from ..experiments import bench\n",
        "dcdi_core/experiments/y.py": "from . import bench\nfrom ..models.olf import train\n",
        "dcdi_core/pipeline.py": "from blender_addon.factory import batch\ntext = 'import bpy'\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    found = {f.split(" (")[0] for f in violations(tmp_path)}
    runtime = "dcdi_core/models/runtime/"
    assert found == {
        runtime + "__init__.py:1: imports dcdi_core.models.depth.arch",
        runtime + "__init__.py:1: imports dcdi_core.models.depth.arch.DepthNet",
        runtime + "bad.py:6: imports torch.nn",
        runtime + "bad.py:7: imports dcdi_core.models.olf",
        runtime + "bad.py:7: imports dcdi_core.models.olf.arch",
        runtime + "bad.py:8: imports dcdi_core.models.common",
        runtime + "bad.py:9: imports dcdi_core.models.dacn.train",
        "dcdi_core/render/x.py:2: imports dcdi_core.experiments",
        "dcdi_core/render/x.py:2: imports dcdi_core.experiments.bench",
        "dcdi_core/render/x.py:3: imports bpy",
        "dcdi_core/pipeline.py:1: imports blender_addon.factory",
        "dcdi_core/pipeline.py:1: imports blender_addon.factory.batch",
        "dcdi_core/correct/y.py:1: imports dcdi_core.models.runtime.library",
        "dcdi_core/correct/y.py:1: imports dcdi_core.models.runtime.library.psf_source",
    }
