"""Model checkpoints: one file with weights, the full model config, units and version.

The file is a plain dictionary saved with ``torch.save`` and read back with
``torch.load(..., weights_only=True)``, so loading never unpickles arbitrary objects.
Writes go to a temporary file that is renamed into place (an interrupted save never leaves a
corrupt checkpoint).

Format 2 (the short-range families): ``config`` is :meth:`ModelConfig.to_dict` (``family``,
``short_range`` parameters, cutoff, electrostatics) and the short-range weights are
``short_range.*``. Format 1 files (SchNet only: a flat config and ``schnet.*`` weights) are
read as format 2 by :func:`read_checkpoint`, unchanged on disk.
"""

from __future__ import annotations

from pathlib import Path

import torch

from emlpack import __version__
from emlpack._files import atomic_path
from emlpack.errors import EmlpackError
from emlpack.nn.potential import EMLP, ModelConfig

FORMAT = "emlpack-model"
FORMAT_VERSION = 2
#: the short-range weights' prefix in format 1 (SchNet, before the families)
_V1_PREFIX = "schnet."
UNITS = {"energy": "eV", "length": "Å", "force": "eV/Å", "field": "V/Å", "stress": "eV/Å^3"}


class CheckpointError(EmlpackError, ValueError):
    """A file that is not an emlpack model checkpoint (or is damaged)."""


def save_model(model: EMLP, path: str | Path, metadata: dict | None = None) -> Path:
    """Write ``model`` (weights as stored, config, units, version, ``metadata``) to ``path``."""
    path = Path(path)
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "emlpack_version": __version__,
        "config": model.config.to_dict(),
        "units": dict(UNITS),
        "dtype": str(next(model.parameters()).dtype).replace("torch.", ""),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "metadata": dict(metadata or {}),
    }
    # through a file object: the archive's records are then named "archive/...", not after
    # the temporary file, so the same model and metadata always give the same bytes (a
    # committed snapshot or pretrained file written again adds nothing to the repository)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(payload, f)
    return path


def read_checkpoint(path: str | Path) -> dict:
    """The checkpoint dictionary, validated, in the current format (older formats are
    converted in memory); raises :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign files
        raise CheckpointError(
            f"{path}: not an emlpack model checkpoint (cannot be read safely: {exc})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an emlpack model checkpoint (no '{FORMAT}' marker)")
    if payload.get("format_version", 0) > FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format {payload['format_version']} is newer than this emlpack"
            f" ({__version__}) understands"
        )
    for key in ("config", "state_dict"):
        if key not in payload:
            raise CheckpointError(f"{path}: checkpoint lacks {key!r}")
    if payload.get("format_version", 0) < 2:
        payload = _from_format_1(payload, path)
    return payload


def _from_format_1(payload: dict, path: Path) -> dict:
    """A format-1 payload as format 2: the flat config nested (family ``schnet``), the
    ``schnet.*`` weights renamed ``short_range.*``."""
    try:
        config = ModelConfig.from_dict(payload["config"]).to_dict()
    except (ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: inconsistent checkpoint: {exc}") from None
    state = {("short_range." + k[len(_V1_PREFIX):] if k.startswith(_V1_PREFIX) else k): v
             for k, v in payload["state_dict"].items()}
    return {**payload, "format_version": 2, "config": config, "state_dict": state}


def load_model(path: str | Path, dtype: torch.dtype | None = torch.float64) -> EMLP:
    """The :class:`EMLP` stored in ``path``, cast to ``dtype`` (None: as stored)."""
    payload = read_checkpoint(path)
    try:
        model = EMLP(ModelConfig.from_dict(payload["config"]))
        model.load_state_dict(payload["state_dict"])
    except (ValueError, TypeError, RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: inconsistent checkpoint: {exc}") from None
    model.eval()
    return model.to(dtype) if dtype is not None else model
