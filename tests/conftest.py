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
