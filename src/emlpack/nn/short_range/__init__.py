"""Short-range families of the eMLP: one protocol, a registry, the families.

:mod:`~emlpack.nn.short_range.protocol` says what a family is (atomic energies from atomic
numbers, half-list edge vectors and the edge list) and which optional capabilities it may
offer; :mod:`~emlpack.nn.short_range.registry` builds a family from its name;
:mod:`~emlpack.nn.short_range.hessian` differentiates any family twice (exactly).

Registered here:

* ``"schnet"``: :class:`~emlpack.nn.short_range.schnet.SchNet`, the paper's network, with
  every capability;
* ``"painn"``: :class:`emlpack.nn.short_range.painn.PaiNN` (issue 48), registered when its
  module is part of the installed package.
"""

from __future__ import annotations

import importlib
import importlib.util

from emlpack.nn.short_range.protocol import (
    FrozenAnyDtype,
    HeldEdges,
    HoldsEdges,
    LengthGradient,
    LengthHessian,
    ShortRange,
    TabulatesEdges,
    VectorGradient,
)
from emlpack.nn.short_range.registry import (
    FamilyError,
    build_short_range,
    families,
    family_defaults,
    register_family,
    resolve_params,
)
from emlpack.nn.short_range.schnet import SCHNET_DEFAULTS, SchNet

__all__ = [
    "FamilyError",
    "FrozenAnyDtype",
    "HeldEdges",
    "HoldsEdges",
    "LengthGradient",
    "LengthHessian",
    "ShortRange",
    "TabulatesEdges",
    "VectorGradient",
    "build_short_range",
    "families",
    "family_defaults",
    "register_family",
    "resolve_params",
]

register_family("schnet", SchNet, SCHNET_DEFAULTS)

# PaiNN: registered once its module is in the package (found, then imported: an error inside
# it is raised, not hidden); its parameters and defaults are its constructor's
if importlib.util.find_spec(f"{__name__}.painn") is not None:
    register_family("painn", importlib.import_module(f"{__name__}.painn").PaiNN)
