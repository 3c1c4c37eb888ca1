"""The package's modules form layers: the graph of every import of one of its modules by
another (module-level and inside functions, read from the source) has no cycle and no import
goes up a layer of :data:`LAYERS`; every module declares ``__all__`` and modules take from each
other only what is there; a module over 400 lines names its one concern; every module imports
on its own in a fresh interpreter (oracles: Tarjan's strongly connected components of the
graph read by ``ast``; the interpreter)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "jaxfalsify"


def modules() -> dict[str, Path]:
    out = {}
    for p in sorted(ROOT.rglob("*.py")):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in known else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in known and m != name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_known_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]


# The package's layers, lowest first, one folder each: a module imports only from its own
# layer or below. The package's top holds only the interface (the CLI and the package itself).
LAYER_FOLDERS = ["base", "io", "scenario", "suts", "core", "search", "engine", "outputs", "jobs"]
LAYERS = {**{f: [f, f + ".*"] for f in LAYER_FOLDERS}, "interface": ["cli", "__main__", ""]}


def layer_of(module: str) -> int:
    """The index in :data:`LAYERS` of ``jaxfalsify.<module>``."""
    short = module.removeprefix("jaxfalsify").removeprefix(".")
    for i, names in enumerate(LAYERS.values()):
        for n in names:
            if short == n or (n.endswith(".*") and short.startswith(n[:-1])):
                return i
    raise KeyError(f"{module} is in no layer of LAYERS")


def upward(graph: dict[str, set[str]]) -> list[str]:
    """Imports of a module in a higher layer."""
    return sorted(f"{a} -> {b}" for a, bs in graph.items() for b in bs
                  if layer_of(b) > layer_of(a))


def test_the_layer_check_finds_an_upward_import():
    graph = {"jaxfalsify.core.sim": {"jaxfalsify.outputs.figures", "jaxfalsify.scenario.space"},
             "jaxfalsify.outputs.figures": {"jaxfalsify.core.sim"}}
    assert upward(graph) == ["jaxfalsify.core.sim -> jaxfalsify.outputs.figures"]


def test_every_module_imports_only_from_its_layer_or_below():
    mods = modules()
    for m in mods:  # every module is in a layer (KeyError otherwise)
        layer_of(m)
    graph = {m: imports_of(m, p, set(mods)) for m, p in mods.items()}
    assert graph["jaxfalsify.cli"], "the graph was not read"
    assert upward(graph) == []


def test_the_package_has_no_import_cycle():
    mods = modules()
    graph = {m: imports_of(m, p, set(mods)) for m, p in mods.items()}
    assert len(graph) > 30 and graph["jaxfalsify.jobs.runs"], "the graph was not read"
    assert cycles(graph) == []


@pytest.mark.slow
def test_every_module_imports_alone():
    failed = []
    for name in modules():
        r = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True,
                           text=True, timeout=120)
        if r.returncode:
            failed.append(f"{name}: {r.stderr.strip().splitlines()[-1]}")
    assert failed == []


def test_a_module_over_400_lines_names_its_one_concern():
    long = {m: p for m, p in modules().items() if len(p.read_text().splitlines()) > 400}
    assert long, "no long module found: the line count was not read"
    unsaid = [m for m, p in long.items()
              if "One concern" not in (ast.get_docstring(ast.parse(p.read_text())) or "")]
    assert unsaid == []


def names_taken(mods: dict[str, Path]) -> dict[str, set[str]]:
    """For each module, the names other modules of the package take from it: ``from M import
    name`` and ``alias.name`` where ``alias`` is M imported under a name."""
    taken: dict[str, set[str]] = {m: set() for m in mods}
    for me, path in mods.items():
        tree = ast.parse(path.read_text())
        alias = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxfalsify"):
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    if full in mods:
                        alias[a.asname or a.name] = full
                    elif node.module in mods and node.module != me:
                        taken[node.module].add(a.name)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and alias.get(node.value.id, me) != me):
                taken[alias[node.value.id]].add(node.attr)
    return taken


def top_level_names(path: Path) -> set[str]:
    """Names a module binds at its top level (within ``if`` and ``try`` blocks too)."""
    out, todo = set(), list(ast.parse(path.read_text()).body)
    while todo:
        n = todo.pop()
        if isinstance(n, (ast.FunctionDef, ast.ClassDef)):
            out.add(n.name)
        elif isinstance(n, (ast.Assign, ast.AnnAssign)):
            out |= {t.id for t in (n.targets if isinstance(n, ast.Assign) else [n.target])
                    if isinstance(t, ast.Name)}
        elif isinstance(n, (ast.Import, ast.ImportFrom)):
            out |= {(a.asname or a.name).split(".")[0] for a in n.names}
        elif isinstance(n, (ast.If, ast.Try)):
            todo += n.body + n.orelse
    return out


def declared_all(path: Path) -> list[str] | None:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__"
                                                for t in node.targets):
            return [e.value for e in node.value.elts]
    return None


def test_names_taken_are_read_from_imports_and_attributes(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("from jaxfalsify.b import f\nfrom jaxfalsify import b as bee\nbee.g()\n")
    b.write_text("__all__ = ['f']\ndef f(): pass\ndef g(): pass\n")
    taken = names_taken({"jaxfalsify.a": a, "jaxfalsify.b": b})
    assert taken == {"jaxfalsify.a": set(), "jaxfalsify.b": {"f", "g"}}
    assert declared_all(b) == ["f"]


def test_modules_use_only_each_others_public_api():
    """Every module declares ``__all__``; what one module takes from another is in the
    other's ``__all__``, and every name there is defined."""
    mods = {m: p for m, p in modules().items() if not m.endswith("__main__")}
    taken = names_taken(mods)
    assert taken["jaxfalsify.core.sim"], "no use of sim was read"
    missing, outside, undefined = [], [], []
    for m, p in mods.items():
        names = declared_all(p)
        if names is None:
            missing.append(m)
            continue
        outside += [f"{m}.{n}" for n in sorted(taken[m] - set(names))
                    if f"{m}.{n}" not in mods and not n.startswith("__")]
        undefined += [f"{m}.{n}" for n in names if n not in top_level_names(p)]
    assert (missing, outside, undefined) == ([], [], [])
