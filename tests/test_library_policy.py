"""Rules of the library code (DESIGN.md, STYLE.md), checked on the source: one error base, one
logging style (the library logs through ``logging.getLogger(__name__)`` and installs no handler;
only the CLI and the demo print), imports without cycles and without other modules' private
names (function-local imports included)."""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "emlpack"
#: modules that talk to the user directly: the command line and the demo's progress report
PRINTING = ("cli/",)


def _modules():
    for path in sorted(SRC.rglob("*.py")):
        yield path.relative_to(SRC).as_posix(), ast.parse(path.read_text(), str(path))


def test_every_error_class_derives_from_emlpack_error_and_shadows_no_builtin():
    classes = {}
    for rel, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                classes[node.name] = (rel, [ast.unparse(b).split(".")[-1] for b in node.bases])

    def derives(name, seen=()):
        if name == "EmlpackError":
            return True
        if name not in classes or name in seen:
            return False
        return any(derives(b, (*seen, name)) for b in classes[name][1])

    exceptions = [n for n, (_, bases) in classes.items()
                  if any(b.endswith(("Error", "Exception")) for b in bases) or n.endswith("Error")]
    assert "EmlpackError" in exceptions and len(exceptions) > 10
    bad = [f"{classes[n][0]}: {n}{tuple(classes[n][1])}" for n in exceptions
           if n != "EmlpackError" and not derives(n)]
    shadow = [f"{classes[n][0]}: {n}" for n in exceptions if hasattr(builtins, n)]
    assert not bad, bad
    assert not shadow, shadow


def test_the_library_logs_and_only_the_cli_prints():
    prints, handlers = [], []
    for rel, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.Name) and node.id == "print" and not rel.startswith(PRINTING):
                prints.append(f"{rel}:{node.lineno}")  # a call or a print callable default
            if (isinstance(node, ast.Attribute) and node.attr in ("addHandler", "basicConfig")
                    and not rel.startswith(PRINTING)):
                handlers.append(f"{rel}:{node.lineno}")
    assert not prints, prints
    assert not handlers, handlers


def _module_name(rel: str) -> str:
    parts = ["emlpack", *rel[:-3].split("/")]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports():
    """(importer, imported module, names, line) for every import of emlpack, at any depth."""
    modules = {_module_name(rel) for rel, _ in _modules()}
    for rel, tree in _modules():
        me = _module_name(rel)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("emlpack."):
                        yield me, alias.name, [], f"{rel}:{node.lineno}"
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("emlpack"):
                names = [a.name for a in node.names]
                yield me, node.module, names, f"{rel}:{node.lineno}"
                for name in names:  # `from emlpack.pairs import relax`: the submodule
                    if f"{node.module}.{name}" in modules:
                        yield me, f"{node.module}.{name}", [], f"{rel}:{node.lineno}"


def test_no_module_imports_another_modules_private_names():
    bad = [f"{where}: {name} from {module}" for me, module, names, where in _imports()
           for name in names if name.startswith("_") and not name.startswith("__")
           and module != me]
    assert not bad, bad


def test_no_import_cycles():
    """No module imports one that imports it back (directly or through others), counting
    function-local imports; a package's ``__init__`` re-exporting its own submodules is the
    one allowed direction."""
    graph: dict[str, set[str]] = {}
    for me, module, _, _ in _imports():
        if module != me and not (me.startswith(module + ".")):  # a submodule and its package
            graph.setdefault(me, set()).add(module)
    cycles, state = [], {}

    def visit(node, path):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert len(graph) > 50
    assert not cycles, cycles
