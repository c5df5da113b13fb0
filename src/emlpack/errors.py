"""The one base class of emlpack's errors.

Every error a user can cause (a bad file, model, structure or argument) derives from
:class:`EmlpackError`; its message is one line naming the file, the frame and the problem, so
the command line prints it without a traceback. Each area keeps its own subclass (e.g.
``StructureError``, ``StoreError``), which also derives from the matching built-in exception
(``ValueError``, ``RuntimeError``) so existing ``except`` clauses keep working.
"""

from __future__ import annotations

__all__ = ["BrokenResultError", "EmlpackError", "InputError", "MissingDependencyError",
           "MissingFileError", "ModelFileError"]


class EmlpackError(Exception):
    """Base class of every emlpack error (user errors and failed computations)."""


class InputError(EmlpackError, ValueError):
    """A bad command-line argument or input (file, structure, field, run length)."""


class ModelFileError(EmlpackError, ValueError):
    """A model argument that is not an emlpack model file (checked before PyTorch reads it)."""


class MissingFileError(EmlpackError, FileNotFoundError):
    """An input file that does not exist (the message names it)."""


class MissingDependencyError(EmlpackError, ImportError):
    """An optional package that a feature needs is not installed (the message names the pip
    extra that provides it; raised by :func:`emlpack.optional.import_optional`)."""


class BrokenResultError(EmlpackError, RuntimeError):
    """A computation whose result cannot be reported: too few ensemble members (or the single
    model) reached a sound result (e.g. pairs not at a minimum). Not a user error: ``emlp``
    prints the message as one line and exits 3, writing no values."""
