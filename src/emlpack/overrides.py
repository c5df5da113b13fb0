"""``key=value`` overrides of nested YAML settings: the one parser behind ``emlp train``'s
overrides, ``emlp label -s`` / ``emlp campaign`` recipes and the examples' study scripts.

A key is a dotted path into the nested mapping (``training.max_epochs=5``,
``prepare.optimize=false``); the value is parsed as YAML: ``true`` a bool, ``[0, 1]`` a list,
``null`` or nothing None, and, as in YAML 1.2, ``1e-3`` a float (PyYAML's YAML 1.1 reads the
string "1e-3"; :func:`load_yaml`, which also reads the configuration files). Whether an unknown
key is an error is the caller's choice: the training configuration refuses one, recipes and
study configurations add it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

import yaml

from emlpack.errors import InputError

__all__ = ["OverrideError", "apply_overrides", "load_yaml", "nested", "parse_override"]


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, reading exponent floats without a dot (``1e-3``) as floats."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def load_yaml(text: str) -> Any:
    """``yaml.safe_load`` that reads ``1e-3`` as a float (YAML 1.2), not as a string."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)


class OverrideError(InputError):
    """A malformed ``key=value`` override (no ``=``, an empty key, a value that is not YAML)."""


def parse_override(text: str) -> tuple[list[str], Any]:
    """``(key path, value)`` of one ``key=value`` override; the value parsed as YAML."""
    if "=" not in text:
        raise OverrideError(f"override {text!r}: expected key=value, the key a dotted path"
                            f" (e.g. section.key=1)")
    key, value = text.split("=", 1)
    keys = key.strip().split(".")
    if not all(keys):
        raise OverrideError(f"override {text!r}: the key has an empty part")
    try:
        parsed = load_yaml(value) if value != "" else None
    except yaml.YAMLError as exc:
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        raise OverrideError(f"override {text!r}: the value is not valid YAML ({problem})") from None
    return keys, parsed


def nested(keys: list[str], value: Any) -> dict:
    """``{k1: {k2: ... value}}``: one override as a nested mapping, for a checked merge."""
    update: Any = value
    for k in reversed(keys):
        update = {k: update}
    return update


def apply_overrides(settings: dict, overrides: Iterable[str]) -> dict:
    """``settings`` with each override set in place (missing mappings on the path are added);
    returns ``settings``. A path through a value that is not a mapping raises."""
    for text in overrides:
        keys, value = parse_override(text)
        node = settings
        for depth, k in enumerate(keys[:-1]):
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise OverrideError(f"override {text!r}: {'.'.join(keys[:depth + 1])!r} is not"
                                    f" a mapping")
        node[keys[-1]] = value
    return settings
