"""The add-on's structure, read from its source with ``ast`` (no bpy needed):
one session holds what its functions change between calls, its modules
import each other without a cycle (imports inside functions counted), one
place registers the classes each UI module exports, and no file is long.

The holder count: a module-level name of an add-on module is a *holder*
when a function rebinds it (``global``) or changes it in place (an item or
attribute assigned or deleted, a mutating method such as ``append``,
``clear``, ``update`` or ``pop`` called, or any method called on an
instance of one of the add-on's own classes), through any chain of
attributes and items, and from any add-on module (``from . import m``;
``m.NAME``, ``from .m import NAME``). Module-level code run at import
counts for nothing: constants are built there."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ADDON = ROOT / "blender_addon"
MAX_HOLDERS = 2             # the session, and at most one other
MAX_LINES = 800

MUTATORS = frozenset({"append", "extend", "insert", "remove", "pop", "popitem", "clear", "update", "add", "discard",
                      "setdefault", "sort", "reverse", "difference_update", "intersection_update",
                      "symmetric_difference_update", "move_to_end", "__setitem__", "__delitem__"})
UI_BASES = frozenset({"Operator", "Panel", "PropertyGroup", "Menu", "UIList", "AddonPreferences", "Gizmo",
                      "GizmoGroup", "Header", "KeyingSetInfo", "RenderEngine"})


def addon_modules(folder: Path = ADDON) -> dict[str, ast.Module]:
    """The add-on's own modules (the package's top level, not factory/ or tools/), parsed."""
    return {p.stem: ast.parse(p.read_text(encoding="utf-8"), str(p)) for p in sorted(folder.glob("*.py"))}


def _top_level_names(tree: ast.Module) -> dict[str, ast.AST | None]:
    """Names bound by assignments at a module's top level (not imports,
    functions or classes), with the value each was first bound to."""
    out: dict[str, ast.AST | None] = {}

    def visit(body):
        for node in body:
            if isinstance(node, ast.Assign):
                for t in node.targets:
                    for n in ast.walk(t):
                        if isinstance(n, ast.Name):
                            out.setdefault(n.id, node.value)
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
                out.setdefault(node.target.id, getattr(node, "value", None))
            elif isinstance(node, (ast.If, ast.Try, ast.With)):
                visit(node.body)
                for extra in ("orelse", "finalbody"):
                    visit(getattr(node, extra, []))
                for h in getattr(node, "handlers", []):
                    visit(h.body)
    visit(tree.body)
    return out


def _addon_imports(tree: ast.Module, modules) -> dict[str, tuple[str, str | None]]:
    """Local name -> (add-on module, name in it; None for the module itself),
    of every import of an add-on module in the file, at any depth."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1:
                base = node.module
            elif node.level == 0 and (node.module or "").startswith("blender_addon"):
                base = node.module.removeprefix("blender_addon").lstrip(".") or None
            else:
                continue
            for a in node.names:
                local = a.asname or a.name
                if base is None and a.name in modules:
                    out[local] = (a.name, None)
                elif base is not None and base.split(".")[0] in modules:
                    out[local] = (base.split(".")[0], a.name)
    return out


def _bound_here(fn) -> tuple[set[str], set[str]]:
    """(locals, globals) of a function or lambda: its arguments and the names
    it stores, less those it declares global; nested functions not entered."""
    args = fn.args
    local = {a.arg for a in (*args.posonlyargs, *args.args, *args.kwonlyargs)}
    local |= {a.arg for a in (args.vararg, args.kwarg) if a is not None}
    declared: set[str] = set()
    body = fn.body if isinstance(fn.body, list) else [fn.body]
    stack = list(body)
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Global):
            declared.update(node.names)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, (ast.Store, ast.Del)):
            local.add(node.id)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            local.add(node.name)
            continue
        elif isinstance(node, ast.Lambda):
            continue
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            local.update((a.asname or a.name).split(".")[0] for a in node.names)
        stack.extend(ast.iter_child_nodes(node))
    return local - declared, declared


def _outermost_functions(node):
    """The functions and lambdas under ``node`` not inside another one (methods included)."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            yield child
        else:
            yield from _outermost_functions(child)


def holders(folder: Path = ADDON) -> set[tuple[str, str]]:
    """(module, name) of every module-level holder of the add-on in ``folder``
    (see the module docstring)."""
    modules = addon_modules(folder)
    top = {m: _top_level_names(t) for m, t in modules.items()}
    classes = {n.name for t in modules.values() for n in t.body if isinstance(n, ast.ClassDef)}
    found: set[tuple[str, str]] = set()

    def instance_of_addon_class(value) -> bool:
        if not isinstance(value, ast.Call):
            return False
        f = value.func
        return (isinstance(f, ast.Name) and f.id in classes) or (isinstance(f, ast.Attribute) and f.attr in classes)

    for mod, tree in modules.items():
        imports = _addon_imports(tree, modules)

        def resolve(expr, hidden: set[str]) -> tuple[str, str] | None:
            """The holder ``expr`` (a name, with attributes and items) is part of, or None."""
            chain = []
            while isinstance(expr, (ast.Attribute, ast.Subscript)):
                if isinstance(expr, ast.Attribute):
                    chain.append(expr.attr)
                expr = expr.value
            if not isinstance(expr, ast.Name) or expr.id in hidden:
                return None
            chain.reverse()
            if expr.id in imports:
                m, name = imports[expr.id]
                if name is None:                     # m.NAME...: a name of module m
                    if not chain:
                        return None
                    name = chain[0]
                return (m, name) if name in top[m] else None
            return (mod, expr.id) if expr.id in top[mod] else None

        def visit(fn, hidden_outer: set[str]):
            local, declared = _bound_here(fn)
            hidden = (hidden_outer | local) - declared
            for name in declared:
                if name in top[mod] or any(isinstance(n, ast.Name) and n.id == name and isinstance(n.ctx, ast.Store)
                                           for n in ast.walk(fn)):
                    found.add((mod, name))
            body = fn.body if isinstance(fn.body, list) else [fn.body]
            stack = list(body)
            while stack:
                node = stack.pop()
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                    visit(node, hidden)
                    continue
                targets = []
                if isinstance(node, ast.Assign):
                    targets = node.targets
                elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
                    targets = [node.target]
                elif isinstance(node, ast.Delete):
                    targets = node.targets
                for t in targets:
                    for part in (t.elts if isinstance(t, (ast.Tuple, ast.List)) else [t]):
                        if isinstance(part, (ast.Attribute, ast.Subscript)):
                            h = resolve(part, hidden)
                            if h:
                                found.add(h)
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                    h = resolve(node.func.value, hidden)
                    if h and (node.func.attr in MUTATORS or instance_of_addon_class(top[h[0]].get(h[1]))):
                        found.add(h)
                stack.extend(ast.iter_child_nodes(node))

        for fn in _outermost_functions(tree):
            visit(fn, set())
    return found


def import_graph(folder: Path = ADDON) -> dict[str, set[str]]:
    """Which add-on module imports which, imports inside functions counted."""
    modules = addon_modules(folder)
    graph = {m: set() for m in modules}
    for mod, tree in modules.items():
        for local, (m, _) in _addon_imports(tree, modules).items():
            if m != mod:
                graph[mod].add(m)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every import cycle of ``graph`` found by a depth-first walk (each as the path that closes it)."""
    found, state = [], {}

    def walk(node, path):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                found.append(path[path.index(nxt):] + [node, nxt] if nxt in path else [node, nxt])
            elif nxt not in state:
                walk(nxt, path + [node])
        state[node] = "done"
    for n in sorted(graph):
        if n not in state:
            walk(n, [])
    return found


# ------------------------------------------------------------------ the detectors catch what they must
def _write(folder: Path, files: dict[str, str]) -> Path:
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text)
    return folder


def test_the_holder_count_sees_every_way_of_holding(tmp_path):
    folder = _write(tmp_path / "pkg", {
        "a.py": "CACHE = {}\nJOBS = set()\nLAST = {}\nCOUNT = 0\nITEMS = []\nNAMES = ('x',)\n"
                "class State:\n    pass\nSTATE = State()\nWORDS = {'a': 1}\n"
                "def f(k):\n    CACHE[k] = 1\n    JOBS.add(k)\n    return WORDS.get(k), NAMES.index(k)\n"
                "def g():\n    global COUNT\n    COUNT += 1\n"
                "def h(items):\n    items.append(1)\n    CACHE = {}\n    CACHE[1] = 2\n"
                "def s():\n    STATE.tick()\n",
        "b.py": "from . import a\nfrom .a import ITEMS\n"
                "def k():\n    a.LAST.update(x=1)\n    ITEMS[:] = [1]\n    return lambda: a.CACHE.clear()\n",
        "c.py": "TABLE = {}\nTABLE['built at import'] = 1\n"})
    assert holders(folder) == {("a", "CACHE"), ("a", "JOBS"), ("a", "COUNT"), ("a", "LAST"), ("a", "ITEMS"),
                               ("a", "STATE")}


def test_the_cycle_check_counts_imports_inside_functions(tmp_path):
    folder = _write(tmp_path / "pkg", {
        "a.py": "from . import b\n", "b.py": "def f():\n    from . import c\n",
        "c.py": "def g():\n    from .a import x\n", "d.py": "from . import a\n"})
    assert [sorted(set(c)) for c in cycles(import_graph(folder))] == [["a", "b", "c"]]


# ------------------------------------------------------------------ the add-on
def test_the_add_on_holds_its_state_in_one_session():
    found = holders()
    assert len(found) <= MAX_HOLDERS, f"module-level holders changed by functions: {sorted(found)}"
    assert ("session", "SESSION") in found


def test_the_add_on_modules_import_without_a_cycle():
    graph = import_graph()
    assert cycles(graph) == [], graph
    assert not graph["session"] and graph["logic"] <= {"session"}     # the bottom: no bpy, no UI


def test_one_place_registers_the_classes_each_ui_module_exports():
    modules = addon_modules()
    for mod, tree in modules.items():
        text = (ADDON / f"{mod}.py").read_text(encoding="utf-8")
        if mod != "__init__":
            assert "register_class" not in text, f"{mod}.py registers classes: __init__.py does"
        ui = [n.name for n in tree.body if isinstance(n, ast.ClassDef)
              and any(isinstance(b, ast.Attribute) and b.attr in UI_BASES for b in n.bases)]
        if not ui:
            continue
        exported = next((n.value for n in tree.body if isinstance(n, ast.Assign)
                         and any(isinstance(t, ast.Name) and t.id == "CLASSES" for t in n.targets)), None)
        assert isinstance(exported, ast.Tuple), f"{mod}.py defines {ui} but no CLASSES tuple"
        assert sorted(e.id for e in exported.elts) == sorted(ui), mod
        assert mod in (ADDON / "__init__.py").read_text(encoding="utf-8"), mod


@pytest.mark.parametrize("path", sorted(ADDON.glob("*.py")), ids=lambda p: p.name)
def test_no_file_is_long(path):
    assert len(path.read_text(encoding="utf-8").splitlines()) <= MAX_LINES
