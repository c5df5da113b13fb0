"""Shared test helpers: paths into ../shared (skip on a user's clone, fail on CI)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def shared_path(relative: str) -> Path:
    """Path of a file under ../shared; skip when absent, but fail when CI=true."""
    path = SHARED / relative
    if not path.exists():
        message = f"{path} is not available (../shared is only present beside the project on CI)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path


def require(module: str):
    """Import an optional dependency that the project installs (an extra of pyproject.toml):
    skip when absent on a user's machine, but fail when CI=true (`pytest.importorskip` would
    skip silently on CI too)."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        message = f"{module} is not installed ({exc}); `make install` installs it"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
