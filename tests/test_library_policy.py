"""Rules of the library code (DESIGN.md, STYLE.md), checked on the source: one error base, one
logging style (the library logs through ``logging.getLogger(__name__)`` and installs no handler;
only the CLI and the demo print)."""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "emlpack"
#: modules that talk to the user directly: the command line and the demo's progress report
PRINTING = ("cli/", "demo.py")


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
