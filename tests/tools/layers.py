"""The layer rule of ``quick_stream`` (docs/architecture.md, "Modules and layers"), checked on the source.

Layers, lowest first: ``core < stream < io < quality < bench < cli``. A module may import its own
layer or a lower one, never a higher one. The services (the repo's ``services/`` folder, installed
as ``quick_stream.services``) may import only ``core``, ``stream`` and ``io`` (and each other); no
layer imports the services, and nothing imports a top-level ``services`` package. ``core`` is pure
computation: besides no higher layer it imports none of :data:`CORE_FORBIDDEN` (zenoh, mcap,
argparse, files, processes, sockets). Every module lives in a layer's folder; only the package's
``__init__`` and ``__main__`` (the command's entry point) sit at its root.

Every ``import`` and ``from ... import`` counts, absolute or relative, at module level or inside a
function (``TYPE_CHECKING`` blocks included), and so does ``importlib.import_module("...")`` with a
literal name. And no import cycle between modules (:func:`find_cycles`: the same imports, a function's
deferred import included, which is how a cycle hides). ``python -m tests.tools.layers [ROOT]`` prints
each violation and each cycle and exits 1 if any.
"""
from __future__ import annotations

import argparse

import ast
import functools
import sys
from dataclasses import dataclass
from pathlib import Path

LAYERS = ("core", "stream", "io", "quality", "bench", "cli")
RANK = {name: i for i, name in enumerate(LAYERS)}
SERVICES_MAY_IMPORT = {"core", "stream", "io", "services"}
CORE_FORBIDDEN = {"zenoh", "mcap", "argparse", "pathlib", "shutil", "subprocess", "socket", "tempfile", "os"}
PACKAGE = "quick_stream"


@dataclass(frozen=True)
class Violation:
    path: str  # relative to the checked root
    line: int
    importer: str  # the importing module's layer
    imported: str  # the module imported
    why: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.importer} imports {self.imported}: {self.why}"


def module_of(rel: Path) -> tuple[str, bool]:
    """(dotted module name, is a package's __init__) of a file relative to the root: ``services/x.py``
    is ``quick_stream.services.x``."""
    parts = list(rel.with_suffix("").parts)
    if parts[0] == "services":
        parts = [PACKAGE, *parts]
    is_pkg = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_pkg else parts), is_pkg


def layer_of(module: str) -> str | None:
    """The layer of a module of the package: a layer name, ``services``, ``root`` (the package's own
    ``__init__``/``__main__``), or None for a module outside the package."""
    parts = module.split(".")
    if parts[0] != PACKAGE:
        return None
    if len(parts) == 1:
        return "root"
    if parts[1] in RANK or parts[1] == "services":
        return parts[1]
    return "root"  # quick_stream.__main__ (and any other module at the package root)


def imported_modules(tree: ast.AST, module: str, is_pkg: bool) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in ``tree``; ``from X import name`` counts as ``X.name``
    (a submodule or a name of X: either way it comes from X's layer)."""
    package = module if is_pkg else module.rpartition(".")[0]
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out += [(node.lineno, f"{target}.{a.name}" if a.name != "*" else target) for a in node.names]
        elif isinstance(node, ast.Call) and _literal_import_module(node):
            out.append((node.lineno, node.args[0].value))
    return out


def _literal_import_module(call: ast.Call) -> bool:
    """``importlib.import_module("absolute.name")`` (or ``import_module(...)``) with a literal name."""
    name = getattr(call.func, "attr", getattr(call.func, "id", None))
    arg = call.args[0] if call.args else None
    return (name == "import_module" and isinstance(arg, ast.Constant) and isinstance(arg.value, str)
            and not arg.value.startswith("."))


def check_import(importer: str, imported: str) -> str | None:
    """Why importing ``imported`` from a module of layer ``importer`` breaks the rule, or None."""
    top = imported.split(".")[0]
    if top == "services":
        return "the services are quick_stream.services, never a top-level `services` package"
    if importer == "core" and top in CORE_FORBIDDEN:
        return f"core is pure computation: no {top}"
    target = layer_of(imported)
    if target is None or target == "root":
        return None
    if importer == "services":
        return None if target in SERVICES_MAY_IMPORT else "a service imports only core, stream and io"
    if target == "services":
        return "no layer imports the services"
    if importer == "root":
        return None  # quick_stream/__main__.py: the command's entry point (it imports the cli)
    if RANK[target] > RANK[importer]:
        return f"{target} is above {importer} (core < stream < io < quality < bench < cli)"
    return None


@functools.lru_cache(maxsize=4096)
def _parse_text(text: str) -> ast.Module:
    return ast.parse(text)


def _parse(text: str, name: str) -> ast.Module:
    """A module's syntax tree, parsed once per text (the tests check many copies of one tree; read only)."""
    try:
        return _parse_text(text)
    except SyntaxError:
        return ast.parse(text, name)  # the error again, naming the file


def check_tree(root: Path) -> list[Violation]:
    """Every violation in ``root``/quick_stream and ``root``/services."""
    found: list[Violation] = []
    files = sorted([*(root / PACKAGE).rglob("*.py"), *(root / "services").rglob("*.py")])
    for path in files:
        rel = path.relative_to(root)
        module, is_pkg = module_of(rel)
        importer = layer_of(module)
        if importer == "root" and module not in (PACKAGE, f"{PACKAGE}.__main__"):
            found.append(Violation(str(rel), 1, "root", module, f"a module belongs to a layer ({', '.join(LAYERS)})"))
        tree = _parse(path.read_text(), str(rel))
        for line, imported in imported_modules(tree, module, is_pkg):
            why = check_import(importer, imported)
            if why:
                found.append(Violation(str(rel), line, importer, imported, why))
    return found


def _module_files(root: Path) -> dict[str, tuple[Path, bool]]:
    files = sorted([*(root / PACKAGE).rglob("*.py"), *(root / "services").rglob("*.py")])
    return {m: (path, pkg) for path in files for m, pkg in [module_of(path.relative_to(root))]}


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of the package it imports (``from X import name``: X.name when that is a
    module, else X)."""
    mods = _module_files(root)
    graph: dict[str, set[str]] = {}
    for module, (path, is_pkg) in mods.items():
        tree = _parse(path.read_text(), str(path))
        edges = set()
        for _, imported in imported_modules(tree, module, is_pkg):
            target = imported if imported in mods else imported.rpartition(".")[0]
            if target in mods and target != module:
                edges.add(target)
        graph[module] = edges
    return graph


def find_cycles(root: Path) -> list[list[str]]:
    """Every set of modules that import each other, directly or around a loop (the strongly connected
    components of :func:`import_graph` with more than one module), each sorted."""
    graph = import_graph(root)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
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
    return sorted(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.tools.layers", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", nargs="?", type=Path, default=Path(__file__).resolve().parents[2],
                   help="the repository to check (default: this one)")
    root = p.parse_args(argv).root
    if not (root / "quick_stream").is_dir():
        p.error(f"{root}: no quick_stream package there (give the repository's folder)")
    found = check_tree(root)
    for v in found:
        print(v)
    cycles = find_cycles(root)
    for c in cycles:
        print("import cycle among: " + ", ".join(c))
    print(f"{len(found)} layer violation(s), {len(cycles)} import cycle(s) in {root}")
    return 1 if found or cycles else 0


if __name__ == "__main__":
    sys.exit(main())
