"""The registry of short-range families: a family is built from its name and parameters.

``register_family(name, cls, defaults)`` adds a family, ``build_short_range(family, params,
cutoff=..., cutoff_transition=...)`` builds one (``cls(cutoff=..., cutoff_transition=...,
**params)``, the family's defaults filled in), ``families()`` lists the names and
``family_defaults(name)`` gives a family's parameters with their defaults. The families are
registered in :mod:`emlpack.nn.short_range` (the package's ``__init__``); tests register
their own.
"""

from __future__ import annotations

import copy
import inspect
from dataclasses import dataclass

from torch import nn

from emlpack.errors import EmlpackError

__all__ = ["FamilyError", "build_short_range", "families", "family_defaults",
           "register_family", "resolve_params"]

#: constructor arguments that EMLP passes to every family (the graph's, not the family's)
GRAPH_ARGUMENTS = ("cutoff", "cutoff_transition")


class FamilyError(EmlpackError, ValueError):
    """An unknown short-range family, or parameters that the family does not take."""


@dataclass(frozen=True)
class _Family:
    cls: type[nn.Module]
    defaults: dict


_FAMILIES: dict[str, _Family] = {}


def register_family(name: str, cls: type[nn.Module], defaults: dict | None = None) -> None:
    """Register ``cls`` as the short-range family ``name`` with its parameters ``defaults``
    (None: the keyword defaults of ``cls.__init__`` other than ``cutoff`` and
    ``cutoff_transition``). Registering a name again replaces it only with the same class."""
    if defaults is None:
        defaults = {
            k: p.default for k, p in inspect.signature(cls.__init__).parameters.items()
            if k not in ("self", *GRAPH_ARGUMENTS) and p.default is not inspect.Parameter.empty
        }
    known = _FAMILIES.get(name)
    if known is not None and known.cls is not cls:
        raise FamilyError(f"short-range family {name!r} is already registered"
                          f" ({known.cls.__module__}.{known.cls.__qualname__})")
    clash = sorted(set(defaults) & set(GRAPH_ARGUMENTS))
    if clash:
        raise FamilyError(f"short-range family {name!r}: {clash} are the model's (graph)"
                          " arguments, not family parameters")
    _FAMILIES[name] = _Family(cls, copy.deepcopy(dict(defaults)))


def families() -> tuple[str, ...]:
    """Names of the registered short-range families, in registration order."""
    return tuple(_FAMILIES)


def _family(name: str) -> _Family:
    if name not in _FAMILIES:
        raise FamilyError(f"unknown short-range family {name!r} (known: {', '.join(_FAMILIES)})")
    return _FAMILIES[name]


def family_defaults(name: str) -> dict:
    """The parameters of family ``name`` with their defaults (a copy)."""
    return copy.deepcopy(_family(name).defaults)


def resolve_params(name: str, params: dict | None) -> dict:
    """``params`` of family ``name`` with its defaults filled in; a parameter that the family
    does not take raises :class:`FamilyError`."""
    defaults = _family(name).defaults
    params = dict(params or {})
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise FamilyError(f"short-range family {name!r} has no parameter(s) {unknown}"
                          f" (its parameters: {sorted(defaults)})")
    return {**copy.deepcopy(defaults), **params}


def build_short_range(
    family: str, params: dict | None = None, *, cutoff: float, cutoff_transition: float
) -> nn.Module:
    """The short-range module of ``family`` with ``params`` (defaults filled in) for the
    eMLP's ``cutoff`` and ``cutoff_transition`` (Å)."""
    resolved = resolve_params(family, params)
    return _family(family).cls(cutoff=cutoff, cutoff_transition=cutoff_transition, **resolved)
