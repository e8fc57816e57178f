"""ambfit's modules import downwards only (STYLE.md section 6), and no two of them import each other.

Layers, bottom to top: helpers with no ambfit imports (``_recent``, ``_jaxcache``, ``_output``, ``_arrays``),
``physics``, the low-level infrastructure (``checks``, ``data``, ``engine``, ``workers``), ``rig``, ``estimation``,
``diagnosis``, ``studies``, ``faces``.  A module may import from its own layer and the layers below it.  Every import
counts, wherever it stands: at module level, inside a function, or under ``TYPE_CHECKING`` (a dependency that static
analysers and readers follow all the same).  Within the estimation layer the closed form and the least-squares core
lie below the fit pipeline and must not reach it, through any chain of imports.  The source is read with :mod:`ast`,
not imported, so the check is cheap and sees every import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ambfit"

LAYERS = (
    ("helpers", ("ambfit._recent", "ambfit._jaxcache", "ambfit._output", "ambfit._arrays")),
    ("physics", ("ambfit.physics",)),
    ("infrastructure", ("ambfit.checks", "ambfit.data", "ambfit.rows", "ambfit.engine", "ambfit.workers")),
    ("rig", ("ambfit.rig",)),
    ("estimation", ("ambfit.estimation",)),
    ("rotordynamics", ("ambfit.rotordynamics",)),
    ("diagnosis", ("ambfit.diagnosis",)),
    ("studies", ("ambfit.studies",)),
    ("faces", ("ambfit.faces",)),
)
"""Bottom to top; ``ambfit`` itself (the lazy public API) and ``ambfit.__main__`` sit above them all."""

TOP = ("ambfit", "ambfit.__main__")


def modules(package: Path = PACKAGE) -> dict[str, Path]:
    """Every module of the package by its dotted name (a package by its ``__init__``)."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports(name: str, path: Path, known: dict) -> set[tuple[str, str]]:
    """``(module, imported name)`` pairs of ambfit that ``name`` imports; ``from a import b`` is module ``a.b``
    when that is a module, else ``a``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {(a.name, "") for a in node.names if a.name.split(".")[0] == "ambfit"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([node.module] if node.module else []))
            if base.split(".")[0] != "ambfit":
                continue
            for a in node.names:
                full = f"{base}.{a.name}"
                out.add((full, "") if full in known else (base, a.name))
    return out


def layer(name: str) -> int | None:
    """Index of the layer ``name`` belongs to (its longest listed prefix); None above them all or unlisted."""
    parts = name.split(".")
    for k in range(len(parts), 1, -1):
        prefix = ".".join(parts[:k])
        for j, (_, members) in enumerate(LAYERS):
            if prefix in members:
                return j
    return None


def graph(package: Path = PACKAGE) -> dict[str, set[tuple[str, str]]]:
    known = modules(package)
    return {name: imports(name, path, known) for name, path in known.items()}


def upward(package: Path = PACKAGE) -> list[str]:
    """Every import of a higher layer, as ``"importer -> imported"``."""
    out = []
    for name, targets in graph(package).items():
        if name in TOP:
            continue
        here = layer(name)
        for target, attr in sorted(targets):
            if target == "ambfit":
                if attr != "__version__":          # the version is the one fact the top package holds
                    out.append(f"{name} -> ambfit.{attr} (the lazy public API: import its module instead)")
                continue
            there = layer(target)
            if here is None or there is None:
                out.append(f"{name} -> {target} (not in any layer of LAYERS)")
            elif there > here:
                out.append(f"{name} -> {target} ({LAYERS[here][0]} imports {LAYERS[there][0]})")
    return out


def cycles(package: Path = PACKAGE) -> list[list[str]]:
    """Sets of modules that import each other, directly or through others (Tarjan's strongly connected
    components)."""
    edges = {name: {t for t, _ in targets if t != name and t != "ambfit"} for name, targets in graph(package).items()}
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_every_module_is_in_a_layer():
    unlisted = [name for name in modules() if name not in TOP and layer(name) is None]
    assert not unlisted, f"modules in no layer (add their package to LAYERS): {unlisted}"


def test_no_module_imports_from_a_higher_layer():
    found = upward()
    assert not found, "upward imports:\n" + "\n".join(found)


def test_no_two_modules_import_each_other():
    found = cycles()
    assert not found, "modules that import each other: " + "; ".join(" <-> ".join(c) for c in found)


@pytest.mark.parametrize("a, b", [("ambfit.physics.model", "ambfit.physics.effects")])
def test_the_force_model_and_the_effects_do_not_import_each_other(a, b):
    edges = graph()

    def reaches(src, dst):
        return any(t == dst or t.startswith(dst + ".") for m, targets in edges.items()
                   if m == src or m.startswith(src + ".") for t, _ in targets)

    assert not (reaches(a, b) and reaches(b, a)), f"{a} and {b} import each other"


def reached(src: str, edges: dict) -> dict[str, list[str]]:
    """Every module that the modules of ``src`` (a module or package) import, directly or through others, with the
    chain of imports that gets there."""
    todo = [(m, [m]) for m in sorted(edges) if m == src or m.startswith(src + ".")]
    seen = {m: path for m, path in todo}
    while todo:
        m, path = todo.pop()
        for t, _ in sorted(edges.get(m, ())):
            if t not in seen:
                seen[t] = path + [t]
                todo.append((t, path + [t]))
    return seen


@pytest.mark.parametrize("low, high", [("ambfit.estimation.closed_form", "ambfit.estimation.fit"),
                                       ("ambfit.estimation.core", "ambfit.estimation.fit"),
                                       ("ambfit.estimation.lm", "ambfit.estimation.fit")])
def test_the_closed_form_and_the_core_lie_below_the_fit_pipeline(low, high):
    """Within the estimation layer the closed form (Eq. 5-7, whose solutions start every fit), the least-squares
    core and its solve are below the fit pipeline: none of them imports it, directly or through other modules (a
    function-level import counts: it hides the dependency from a reader, not from the program)."""
    hits = {m: path for m, path in reached(low, graph()).items() if m == high or m.startswith(high + ".")}
    assert not hits, f"{low} reaches {high}: " + "; ".join(" -> ".join(p) for p in hits.values())
