"""``emlp label``, ``relabel``, ``campaign``, ``convert-reference``: reference data and
reference models. Errors are :class:`~emlpack.errors.EmlpackError` s handled by ``emlp``
itself (one line, exit 2)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from emlpack.cli.common import Subparsers, add_parser, positive
from emlpack.errors import InputError

if TYPE_CHECKING:
    import argparse


def add_label(sub: Subparsers) -> None:
    """Register ``emlp label``: sample molecules and label them with DFT into an HDF5 store
    (resumable)."""
    p = add_parser(
        sub, "label", help="sample molecules and label them with DFT into an HDF5 store (resumable)"
    )
    p.add_argument("input", help="SMILES CSV (column 'smiles'), SMILES list, or xyz molecules")
    p.add_argument("-o", "--output", required=True, help="HDF5 dataset store (appended to)")
    p.add_argument("--recipe", help="sampling recipe YAML (default: the paper's eQM7 recipe)")
    p.add_argument("--level", help="labeling level: preset (paper, quick, tiny) or xc/basis")
    p.add_argument("--molecules", help="slice of the input entries, e.g. 0:3")
    p.add_argument("--samples-per-molecule", type=int,
                   help="rescale the recipe's counts to this total per molecule")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=int,
                   help="LocalCluster workers (default: CPU count; 0 = in-process)")
    p.add_argument("--retry-failed", action="store_true", help="label recorded failures again")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE",
                   help="recipe override, repeatable (e.g. -s seed=3 -s prepare.optimize=false)")

    def run(args: argparse.Namespace):
        from emlpack.data.store import StoreError
        from emlpack.qm.labeling import read_molecules, run_labeling
        from emlpack.qm.recipe import load_recipe
        from emlpack.qm.sampling import SamplingError

        positive(args.samples_per_molecule, "--samples-per-molecule")
        positive(args.workers, "--workers", allow_zero=True)
        try:
            overrides = list(args.overrides)
            if args.level:
                overrides.append(f"level={args.level}")
            recipe = load_recipe(args.recipe, overrides, args.samples_per_molecule)
            sources, skipped = read_molecules(args.input, args.molecules)
            summary = run_labeling(sources, args.output, recipe, scheduler=args.scheduler,
                                   workers=args.workers, progress=not args.quiet,
                                   retry_failed=args.retry_failed, skipped=skipped)
        except (SamplingError, StoreError, ValueError) as exc:
            raise InputError(str(exc)) from exc
        print(summary.text())
        return 0

    p.set_defaults(func=run, resumable=True)


def add_relabel(sub: Subparsers) -> None:
    """Register ``emlp relabel``: recompute energy, forces and Foster-Boys centres of an extxyz
    file."""
    p = add_parser(
        sub, "relabel", help="recompute energy, forces and Foster-Boys centres of an extxyz file"
    )
    p.add_argument("input", help="extxyz file (reference convention: Es centres, efield in au)")
    p.add_argument("-o", "--output", required=True, help="output extxyz file")
    p.add_argument("--level", default="paper",
                   help="preset (paper, quick, tiny) or xc/basis[/auxbasis|/nodf]")
    p.add_argument("--index", default=":", help="frames to relabel, ASE slice syntax (e.g. 0:3)")
    p.add_argument("--boys-starts", type=int, default=3, help="Foster-Boys starts per frame")
    p.add_argument("--workers", type=int, default=0,
                   help="Dask LocalCluster workers (default 0: in this process)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace):
        from emlpack.qm.relabel import relabel

        positive(args.boys_starts, "--boys-starts")
        positive(args.workers, "--workers", allow_zero=True)
        try:
            report = relabel(args.input, args.output, level=args.level, index=args.index,
                             boys_starts=args.boys_starts, progress=not args.quiet,
                             workers=args.workers, scheduler=args.scheduler)
        except ValueError as exc:  # ExtxyzError included
            raise InputError(str(exc)) from exc
        print(report.summary())
        return 1 if report.n_failed else 0

    p.set_defaults(func=run)


def add_convert_reference(sub: Subparsers) -> None:
    """Register ``emlp convert-reference``: convert a TensorFlow checkpoint of the authors'
    reference code (no TF needed)."""
    p = add_parser(
        sub, "convert-reference",
        help="convert a TensorFlow checkpoint of the authors' reference code (no TF needed)",
    )
    p.add_argument("prefix", help="checkpoint prefix, e.g. models/eQM7_aug1 (.index/.data/.pickle)")
    p.add_argument("-o", "--output", required=True, help="emlpack model file to write (.pt)")

    def run(args: argparse.Namespace):
        from emlpack.legacy.reference_weights import model_from_reference
        from emlpack.legacy.tf_checkpoint import read_reference_hparams, read_tf_checkpoint
        from emlpack.nn.checkpoint import save_model

        hparams = read_reference_hparams(args.prefix)
        model = model_from_reference(read_tf_checkpoint(args.prefix), hparams, dtype=None)
        meta = {"converted_from": str(args.prefix), "reference_hparams": dict(hparams)}
        save_model(model, args.output, metadata=meta)
        print(f"wrote {args.output}: {model.n_parameters()} parameters")

    p.set_defaults(func=run)


def add_campaign(sub: Subparsers) -> None:
    """Register ``emlp campaign``: a labeling campaign into immutable shards (``init``: molecule
    list and split; ``run``: label, resumable; ``card``: regenerate README.md)."""
    p = add_parser(sub, "campaign", help="a labeling campaign into immutable shards"
                       " (init: molecule list and split; run: label, resumable; card)",
                   threads=False)
    csub = p.add_subparsers(dest="action", required=True)
    pi = csub.add_parser("init", help="fix the molecule list, its seed and the split")
    pi.add_argument("folder", help="data-set folder, e.g. datasets/mini-eqm7")
    pi.add_argument("--smiles", required=True, help="QM7 SMILES CSV (column 'smiles')")
    pi.add_argument("--seed", type=int, default=0, help="sample and split seed (default 0)")
    pi.add_argument("--n-large", type=int, default=100,
                    help="molecules with 6-7 heavy atoms to draw (default 100)")
    pi.add_argument("--samples-per-molecule", type=int, default=6, help="default 6")
    pi.add_argument("--level", default="paper",
                    help="labeling level (default paper; e.g. pbe0/def2-svpd/grid1)")
    pi.add_argument("--exclude", action="append", metavar="FOLDER",
                    help="a pretraining set: every allowed molecule but the validation and"
                         " test molecules of this campaign (repeatable)")
    pi.add_argument("--target", type=int, nargs=2, metavar=("CONFIGURATIONS", "MOLECULES"),
                    help="stop `run` once this many configurations of this many molecules")
    pi.add_argument("--float32", action="store_true",
                    help="shards with float32 positions and forces, compressed (~1 kB per"
                         " configuration)")
    pr = csub.add_parser("run", help="label the next configurations (resumes from the shards)")
    pr.add_argument("folder")
    pr.add_argument("--workers", type=int, default=2,
                    help="labeling processes (default 2: measured faster than 1 x 2 threads)")
    pr.add_argument("--threads", type=int, help="threads per process (default CPUs/workers)")
    pr.add_argument("--hours", type=float, help="stop after this wall time")
    pr.add_argument("--shard-minutes", type=float, default=20.0,
                    help="finished labels become a new shard this often (default 20), once"
                         " there are --shard-min-records of them")
    pr.add_argument("--shard-min-records", type=int, default=None,
                    help="fewest new records (and failures) per shard before the run stops"
                         " (default 10; the last shard takes whatever is left)")
    pr.add_argument("--commit", action="store_true", help="git-commit each new shard")
    pr.add_argument("--quiet", action="store_true", help="no progress bar")
    pr.add_argument("--retry-failed", action="store_true",
                    help="label the recorded failures again (e.g. after a fix of their cause)")
    pr.add_argument("--past-target", action="store_true",
                    help="label every listed molecule, past the target of campaign.yaml")
    pr.set_defaults(resumable=True)
    pc = csub.add_parser("card", help="regenerate README.md from the shards")
    pc.add_argument("folder")

    def run(args: argparse.Namespace):
        import logging

        from emlpack.data.store import StoreError
        from emlpack.qm import campaign
        from emlpack.qm.sampling import SamplingError

        logging.basicConfig(format="%(asctime)s %(name)s: %(message)s")
        logging.getLogger("emlpack").setLevel(logging.INFO)
        try:
            if args.action == "init":
                mols = campaign.init_campaign(args.folder, args.smiles, seed=args.seed,
                                              n_large=args.n_large,
                                              samples_per_molecule=args.samples_per_molecule,
                                              level=args.level, exclude=args.exclude,
                                              target=None if args.target is None else {
                                                  "configurations": args.target[0],
                                                  "molecules": args.target[1]},
                                              storage={"precision": "float32",
                                                       "compress": True}
                                              if args.float32 else None)
                print(f"{args.folder}: {len(mols)} molecules listed")
            elif args.action == "run":
                out = campaign.run_campaign(args.folder, workers=args.workers,
                                            threads=args.threads, hours=args.hours,
                                            shard_minutes=args.shard_minutes,
                                            shard_min_records=campaign.SHARD_MIN_RECORDS
                                            if args.shard_min_records is None
                                            else args.shard_min_records,
                                            commit=args.commit, progress=not args.quiet,
                                            retry_failed=args.retry_failed,
                                            past_target=args.past_target)
                target = out["target"]
                print(f"{args.folder}: {out['new_records']} new configurations,"
                      f" {out['new_failures']} new failures, {len(out['shards'])} shards"
                      f" in {out['wall_s'] / 3600:.2f} h"
                      + (f"; target of {target['configurations']} configurations and"
                         f" {target['molecules']} molecules reached" if target["reached"]
                         else ""))
            else:
                print(campaign.write_card(args.folder))
        except (SamplingError, StoreError, OSError) as exc:
            raise InputError(str(exc)) from exc
        return 0

    p.set_defaults(func=run)


COMMANDS = [add_label, add_relabel, add_convert_reference, add_campaign]
