"""The import graph of the code, read from the source: every import counts,
at the top of a file or inside a function (``import a``, ``from a import b``
where b may be a module, relative imports resolved, ``importlib.
import_module('a')`` and ``__import__('a')`` with a literal name).

The rules, from docs/design.md ("Layers"):

- every module of ``dcdi_core``, ``blender_addon`` and ``lab`` has a layer
  in the table of docs/design.md, and imports only its own layer or lower
  ones (nothing points back up: the engine never imports the add-on or the
  lab, ``psf`` never imports ``render``, ...);
- no cycle between files, within a layer or across;
- the engine never imports Blender (``bpy``, ``bmesh``, ``mathutils``);
- ``dcdi_core.models.runtime`` (numpy only, what the add-on bundles)
  imports neither torch nor the training code; ``render``, ``correct``,
  ``dfd`` and ``psf`` never import torch or ``models`` (a network is handed
  in by the caller, never looked up below it).
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

from lab.layers import TOP, layers, layer_of as _layer, within as _within  # the table, shared with `lab walk`

ROOT = Path(__file__).resolve().parents[1]
BLENDER = ("bpy", "bmesh", "mathutils")
NUMPY_ONLY = ("dcdi_core.models.runtime", "dcdi_core.render", "dcdi_core.correct", "dcdi_core.dfd", "dcdi_core.psf")
NOT_IN_NUMPY_ONLY = ("torch", "dcdi_core.models.olf", "dcdi_core.models.dacn", "dcdi_core.models.depth",
                     "dcdi_core.models.common")
# render/accel_torch.py is the simulation's optional torch accelerator, imported only when asked for
TORCH_ALLOWED = ("dcdi_core.render.accel_torch",)


def module_names(root: Path) -> dict[str, Path]:
    """{dotted module name: file} of every .py file under the top folders of ``root``."""
    out = {}
    for top in TOP:
        for path in sorted((root / top).rglob("*.py")) if (root / top).is_dir() else []:
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def imports_of(path: Path, module: str, modules=()) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of every import in ``path`` (the module
    ``module``); ``from a import b`` gives ``a.b`` (b may be a module) and
    ``a``, unless every b is one of ``modules`` (``from . import x`` imports
    the module x, not its package's __init__ again)."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            head = ".".join(base + ([node.module] if node.module else []))
            names = [f"{head}.{a.name}" for a in node.names if a.name != "*"]
            if not names or any(n not in modules for n in names):
                out.append((node.lineno, head))
            out += [(node.lineno, n) for n in names]
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if (name in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)
                    and isinstance(node.args[0].value, str)):
                out.append((node.lineno, node.args[0].value))
    return out


def graph(root: Path) -> tuple[dict[str, set[str]], list[str]]:
    """({module: modules of the tree it imports}, every (file:line: imports name) of the tree)."""
    mods = module_names(root)
    edges: dict[str, set[str]] = {m: set() for m in mods}
    lines = []
    for m, path in mods.items():
        for line, name in imports_of(path, m, mods):
            lines.append((m, path, line, name))
            target = name
            while target and target not in mods:
                target = target.rpartition(".")[0]
            if target and target != m:
                edges[m].add(target)
    return edges, lines


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter[0]
        counter[0] += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def violations(root: Path, table: dict[str, int]) -> list[str]:
    """Every break of the module docstring's rules in the tree below ``root``."""
    edges, lines = graph(root)
    out = [f"{m}: no layer in docs/design.md" for m in sorted(edges) if _layer(m, table) is None]
    for m, path, line, name in lines:
        where = f"{path.relative_to(root).as_posix()}:{line}: imports {name}"
        mine, theirs = _layer(m, table), _layer(name, table)
        if mine is not None and theirs is not None and theirs > mine:
            out.append(f"{where} (upward: layer {mine} -> {theirs})")
        if m.startswith("dcdi_core") and _within(name, BLENDER):
            out.append(f"{where} (the engine never imports Blender)")
        if (_within(m, NUMPY_ONLY) and not _within(m, TORCH_ALLOWED) and _within(name, NOT_IN_NUMPY_ONLY)):
            out.append(f"{where} (numpy only: no torch, no training code)")
        if _within(m, NUMPY_ONLY[1:]) and _within(name, ("dcdi_core.models",)):
            out.append(f"{where} (a network is handed in, never imported below models)")
    out += [f"cycle: {' -> '.join(c)}" for c in cycles(edges)]
    return sorted(set(out))


def test_the_layers_table_names_every_package():
    table = layers()
    for name in ("dcdi_core.errors", "dcdi_core.io", "dcdi_core.psf", "dcdi_core.render", "dcdi_core.models",
                 "dcdi_core.app", "dcdi_core.cli", "blender_addon", "lab"):
        assert name in table, name
    assert table["dcdi_core.psf"] < table["dcdi_core.render"] < table["dcdi_core.models"] < table["dcdi_core.app"]
    assert table["dcdi_core.cli"] < table["blender_addon"] < table["lab"]


def test_the_tree_has_no_cycle_and_no_upward_import():
    assert violations(ROOT, layers()) == []


def test_the_checker_finds_each_kind_of_break(tmp_path):
    """A cycle closed by an import inside a function, upward imports of each
    form, torch below models; mentions are not imports."""
    files = {
        "dcdi_core/__init__.py": "",
        "dcdi_core/psf/__init__.py": "",
        "dcdi_core/psf/a.py": '"""import torch is only mentioned"""\nfrom . import b\n',
        "dcdi_core/psf/b.py": "def f():\n    from .a import x\n",                        # closes a cycle a <-> b
        "dcdi_core/psf/c.py": "def g():\n    from ..render import simulate\n",          # upward, in a function
        "dcdi_core/render/__init__.py": "",
        "dcdi_core/render/simulate.py": "import importlib\nimportlib.import_module('lab.study')\n",
        "dcdi_core/correct/x.py": "from ..models.runtime import olf\nimport torch\nimport bpy\n",
        "dcdi_core/models/runtime/y.py": "def h():\n    from ..dacn import train\n",
        "dcdi_core/models/runtime/olf.py": "",
        "dcdi_core/models/dacn/train.py": "",
        "dcdi_core/stray.py": "",
        "lab/study.py": "from dcdi_core.psf import a\n",                              # allowed: the lab uses the engine
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    table = {"dcdi_core": 0, "dcdi_core.psf": 2, "dcdi_core.render": 3, "dcdi_core.correct": 3,
             "dcdi_core.models": 4, "lab": 8}
    found = violations(tmp_path, table)
    text = "\n".join(found)
    assert "cycle: dcdi_core.psf.a -> dcdi_core.psf.b" in found
    assert "dcdi_core/psf/c.py:2: imports dcdi_core.render.simulate (upward: layer 2 -> 3)" in found
    assert "dcdi_core/render/simulate.py:2: imports lab.study (upward: layer 3 -> 8)" in found
    assert "dcdi_core/correct/x.py:1: imports dcdi_core.models.runtime.olf (upward: layer 3 -> 4)" in found
    assert "dcdi_core/correct/x.py:2: imports torch (numpy only: no torch, no training code)" in found
    assert "dcdi_core/correct/x.py:3: imports bpy (the engine never imports Blender)" in found
    assert "dcdi_core/models/runtime/y.py:2: imports dcdi_core.models.dacn.train (numpy only: no torch, no training code)" in found
    assert "dcdi_core.stray: no layer in docs/design.md" in found
    assert "lab/study.py" not in text and "only mentioned" not in text


def _reads_args(source: str) -> list[str]:
    """The lines of ``source`` that read an argparse namespace: ``args.x``
    or ``getattr(args, ...)``, a parameter or a name called ``args``."""
    tree = ast.parse(source)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "args":
            found.append(f"line {node.lineno}: args.{node.attr}")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr" \
                and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id == "args":
            found.append(f"line {node.lineno}: getattr(args, ...)")
    return found


def test_no_command_line_namespace_below_cli():
    """The engine below ``cli/`` takes values, not the command line's
    namespace: a job is decided from its request's fields (``cli`` turns
    options into requests)."""
    bad = {}
    for path in sorted((ROOT / "dcdi_core").rglob("*.py")):
        rel = path.relative_to(ROOT / "dcdi_core")
        if rel.parts[0] == "cli":
            continue
        hits = _reads_args(path.read_text(encoding="utf-8"))
        if hits:
            bad[str(rel)] = hits
    assert not bad, bad
    # the check can fail
    assert _reads_args("def f(args):\n    return args.depth, getattr(args, 'x', None)\n") == [
        "line 2: args.depth", "line 2: getattr(args, ...)"]


# the add-on reaches the engine through its application layer and the lens report alone
ADDON_ENGINE_DOORS = ("dcdi_core.app", "dcdi_core.optics.report")
# folders of the add-on that do not ship in it (build.py ADDON_EXCLUDE_DIRS): the factory's batch job and tools
ADDON_APART = ("blender_addon.factory", "blender_addon.tools")


def addon_engine_imports(root: Path) -> dict[str, list[str]]:
    """{add-on module: ['line N: engine module', ...]} of the imports of the
    engine by the modules that ship in the add-on, outside ``app`` and the
    lens report."""
    modules = module_names(root)
    out = {}
    for name, path in modules.items():
        if not name.startswith("blender_addon") or _within(name, ADDON_APART):
            continue
        hits = [f"line {line}: {imp}" for line, imp in imports_of(path, name, modules)
                if _within(imp, ("dcdi_core",)) and not _within(imp, ADDON_ENGINE_DOORS)]
        if hits:
            out[name] = hits
    return out


def test_the_addon_imports_the_engine_through_app_alone(tmp_path):
    """Counted from the files: the add-on's imports of the engine outside
    ``dcdi_core.app`` and the lens report are zero (what it needs, the
    engine serves there: jobs, lenses, thumbnails, pixels, errors)."""
    assert addon_engine_imports(ROOT) == {}
    # the count can fail: an import of an engine module past app, at the top or in a function
    for top in ("blender_addon", "dcdi_core", "dcdi_core/app", "dcdi_core/optics", "dcdi_core/psf"):
        (tmp_path / top).mkdir(parents=True, exist_ok=True)
        (tmp_path / top / "__init__.py").write_text("")
    for name in ("report", "compute"):
        (tmp_path / ("dcdi_core/optics" if name == "report" else "dcdi_core/psf") / f"{name}.py").write_text("")
    (tmp_path / "blender_addon" / "logic.py").write_text(
        "from dcdi_core import app\nfrom dcdi_core.optics import report\n"
        "def f():\n    from dcdi_core.psf import compute\n    import dcdi_core.errors\n")
    assert addon_engine_imports(tmp_path) == {"blender_addon.logic": ["line 4: dcdi_core.psf.compute",
                                                                      "line 5: dcdi_core.errors"]}
