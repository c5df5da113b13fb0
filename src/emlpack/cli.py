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


def _add_relabel(sub) -> None:
    p = sub.add_parser(
        "relabel", help="recompute energy, forces and Foster-Boys centres of an extxyz file"
    )
    p.add_argument("input", help="extxyz file (reference convention: Es centres, efield in au)")
    p.add_argument("-o", "--output", required=True, help="output extxyz file")
    p.add_argument("--level", default="paper",
                   help="preset (paper, quick, tiny) or xc/basis[/auxbasis|/nodf]")
    p.add_argument("--index", default=":", help="frames to relabel, ASE slice syntax (e.g. 0:3)")
    p.add_argument("--boys-starts", type=int, default=3, help="Foster-Boys starts per frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    def run(args):
        from emlpack.qm.refxyz import RefXYZError
        from emlpack.qm.relabel import relabel

        try:
            report = relabel(args.input, args.output, level=args.level, index=args.index,
                             boys_starts=args.boys_starts, progress=not args.quiet)
        except (RefXYZError, ValueError) as exc:
            print(f"emlp relabel: error: {exc}", file=sys.stderr)
            return 2
        print(report.summary())
        return 1 if report.n_failed else 0

    p.set_defaults(func=run)


def _add_convert_reference(sub) -> None:
    p = sub.add_parser(
        "convert-reference",
        help="convert a TensorFlow checkpoint of the authors' reference code (no TF needed)",
    )
    p.add_argument("prefix", help="checkpoint prefix, e.g. models/eQM7_aug1 (.index/.data/.pickle)")
    p.add_argument("-o", "--output", required=True, help="emlpack model file to write (.pt)")

    def run(args):
        from emlpack.io.tf_checkpoint import read_reference_hparams, read_tf_checkpoint
        from emlpack.nn.checkpoint import save_model
        from emlpack.nn.reference import model_from_reference

        hparams = read_reference_hparams(args.prefix)
        model = model_from_reference(read_tf_checkpoint(args.prefix), hparams, dtype=None)
        meta = {"converted_from": str(args.prefix), "reference_hparams": dict(hparams)}
        save_model(model, args.output, metadata=meta)
        print(f"wrote {args.output}: {model.n_parameters()} parameters")

    p.set_defaults(func=run)


COMMANDS = [_add_demo, _add_relabel, _add_convert_reference]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="emlp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
