"""The ``emlp`` command: thin wrappers over the package's modules.

Each sub-command lives in a small ``_add_<name>`` function that registers its arguments and a
handler; handlers import their modules lazily so that ``emlp --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="run the end-to-end demo on the embedded example data")
    p.add_argument("--output", default="demo_output", help="output directory")

    def run(args):
        from emlpack.demo import run_demo

        return run_demo(args.output)

    p.set_defaults(func=run)


COMMANDS = [_add_demo]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="emlp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
