"""The ``emlp`` command: thin wrappers over the package's modules.

One module per command group (:mod:`~emlpack.cli.data`, :mod:`~emlpack.cli.training`,
:mod:`~emlpack.cli.properties`, :mod:`~emlpack.cli.dynamics`), shared arguments and cheap
checks in :mod:`~emlpack.cli.common`, and one error path here: every
:class:`~emlpack.errors.EmlpackError` (bad file, model, structure or argument) is printed as one
line, ``emlp <command>: error: <file, frame: problem>``, and exits 2 (``--debug`` shows the
traceback); a result that cannot be reported (:class:`~emlpack.errors.BrokenResultError`: too
few ensemble members, or the single model, reached a sound result) is one line
``emlp <command>: failed: ...`` and exits 3; Ctrl-C exits 130 and says whether re-running the
command resumes. Handlers import
their modules lazily so that ``emlp --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys

from emlpack.errors import BrokenResultError, EmlpackError, InputError
from emlpack.threads import configure_thread_environment

#: exit status of a user error (as argparse's own), of a result that cannot be reported (as
#: ``emlp md``'s watchdog stop) and of an interrupt (128 + SIGINT)
EXIT_USER_ERROR = 2
EXIT_BROKEN_RESULT = 3
EXIT_INTERRUPTED = 130
#: file-system errors a user causes (a missing input, a folder given for a file)
_FILE_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


def build_parser() -> argparse.ArgumentParser:
    """The ``emlp`` argument parser with every command's sub-parser."""
    from emlpack import __version__
    from emlpack.cli import data, dynamics, properties, training

    parser = argparse.ArgumentParser(
        prog="emlp", description="emlpack: the electron machine-learning potential (eMLP):"
        " label reference data, train, evaluate, and compute properties and MD with a model.",
        epilog="'emlp COMMAND --help' shows a command's options and defaults.")
    parser.add_argument("--version", action="version", version=f"emlpack {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (training, data, properties, dynamics):
        for add in module.COMMANDS:
            add(sub)
    return parser


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line (its class name when it has none)."""
    from emlpack.cli.common import one_line_text

    return one_line_text(exc)


def main(argv: list[str] | None = None) -> int:
    """Run ``emlp`` with ``argv`` (default: the command line); returns the exit status: the
    command's own (0 on success), 2 for a user error, 3 for a result that cannot be reported,
    130 after Ctrl-C."""
    args = build_parser().parse_args(argv)
    debug = getattr(args, "debug", False)
    # before torch is imported: idle OpenMP threads sleep (a busy machine otherwise makes every
    # default-threaded call 10-60x slower, see emlpack.threads); --threads is checked later
    threads = getattr(args, "threads", None)
    configure_thread_environment(threads if isinstance(threads, int) and threads >= 1 else None)
    try:
        if isinstance(threads, int) and threads < 1:
            raise InputError(f"--threads must be at least 1, got {threads}")
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if debug:
            raise
        hint = "; re-run the same command to resume" if getattr(args, "resumable", False) else ""
        print(f"\nemlp {args.command}: interrupted{hint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenResultError as exc:
        if debug:
            raise
        print(f"emlp {args.command}: failed: {one_line(exc)}", file=sys.stderr)
        return EXIT_BROKEN_RESULT
    except (EmlpackError, *_FILE_ERRORS) as exc:
        if debug:
            raise
        print(f"emlp {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return EXIT_USER_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
