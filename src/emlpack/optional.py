"""Optional dependencies: import one, or raise one line that names the pip extra providing it.

The base install (``pip install emlpack``) runs the pretrained and trained models: the ASE
calculator, ``emlp ir``/``polarizability``/``optimize``/``response``/``md`` on xyz files or
SMILES (RDKit is a base dependency), training and evaluation. DFT labeling and the other
optional features import their packages through :func:`import_optional`, which raises a
:class:`~emlpack.errors.MissingDependencyError` (``emlp`` prints it as one line and exits 2)::

    PySCFLabeler (DFT labels) needs pyscf, which is not installed: pip install 'emlpack[qm]'

:data:`PROVIDERS` is the one table of which extra of ``pyproject.toml`` provides which module
(``tests/test_optional_dependencies.py`` checks it against the file). Torch-free.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from emlpack.errors import MissingDependencyError

if TYPE_CHECKING:
    from types import ModuleType

__all__ = ["PROVIDERS", "import_optional", "install_hint", "is_available"]

#: top-level import name -> (the distribution pip installs, the extra of emlpack that lists it;
#: None: a base dependency, e.g. RDKit for ``--smiles``)
PROVIDERS: dict[str, tuple[str, str | None]] = {
    "rdkit": ("rdkit", None),
    "pyscf": ("pyscf", "qm"),
    "dask": ("dask", "qm"),
    "distributed": ("distributed", "qm"),
    "tblite": ("tblite", "qm"),
    "spglib": ("spglib", "periodic"),
    "tensorboard": ("tensorboard", "tensorboard"),
}


def install_hint(module: str) -> str:
    """The pip command that installs the package of ``module`` (an import name of
    :data:`PROVIDERS`, dotted names allowed): ``pip install 'emlpack[qm]'`` for an extra."""
    distribution, extra = _provider(module)
    return f"pip install 'emlpack[{extra}]'" if extra else f"pip install {distribution}"


def import_optional(module: str, purpose: str, alternative: str | None = None) -> ModuleType:
    """``import module`` (e.g. ``"pyscf"``, ``"tblite.ase"``), or raise
    :class:`~emlpack.errors.MissingDependencyError` whose one line says that ``purpose`` needs
    the package, how to install it and, when given, the ``alternative`` that needs none.

    A package that is installed but fails to import (a broken build) is named as such, with
    the import error's first line.
    """
    distribution, extra = _provider(module)
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".")[0]
        missing = isinstance(exc, ModuleNotFoundError) and (
            exc.name is None or exc.name == top or exc.name.startswith(top + "."))
        if missing:
            kind = "which is not installed" if extra else (
                "a dependency of emlpack that is not installed")
            text = f"{purpose} needs {distribution}, {kind}: {install_hint(module)}"
        else:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            text = (f"{purpose} needs {distribution}, which is installed but cannot be imported"
                    f" ({first}); reinstall it: {install_hint(module)}")
        if alternative:
            text += f"; or {alternative}"
        raise MissingDependencyError(text) from exc


def is_available(module: str) -> bool:
    """Whether ``module`` (an import name of :data:`PROVIDERS`) imports: for features that are
    chosen when present (e.g. the Foster-Boys pair guess with PySCF) rather than required."""
    _provider(module)
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def _provider(module: str) -> tuple[str, str | None]:
    top = module.split(".")[0]
    if top not in PROVIDERS:
        raise KeyError(f"{top!r} is not an optional dependency of emlpack (known:"
                       f" {', '.join(sorted(PROVIDERS))})")
    return PROVIDERS[top]
