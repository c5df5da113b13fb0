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
    p.add_argument("--workers", type=int, default=0,
                   help="Dask LocalCluster workers (default 0: in this process)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    def run(args):
        from emlpack.qm.refxyz import RefXYZError
        from emlpack.qm.relabel import relabel

        try:
            report = relabel(args.input, args.output, level=args.level, index=args.index,
                             boys_starts=args.boys_starts, progress=not args.quiet,
                             workers=args.workers, scheduler=args.scheduler)
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


def _add_label(sub) -> None:
    p = sub.add_parser(
        "label", help="sample molecules and label them with DFT into an HDF5 store (resumable)"
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

    def run(args):
        from emlpack.data.store import StoreError
        from emlpack.qm.labeling import read_molecules, run_labeling
        from emlpack.qm.recipe import load_recipe
        from emlpack.qm.sampling import SamplingError

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
            print(f"emlp label: error: {exc}", file=sys.stderr)
            return 2
        print(summary.text())
        return 0

    p.set_defaults(func=run)


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train an eMLP (YAML config + key=value overrides;"
                       " data parallel under torchrun)")
    p.add_argument("config", help="YAML config, e.g. configs/small_cpu.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. training.max_epochs=5")
    p.add_argument("--seeds", type=int, nargs="+", help="train an ensemble, one model per seed")
    p.add_argument("--restart", action="store_true",
                   help="start afresh instead of resuming from <output.dir>/last.pt")

    def run(args):
        from emlpack.data.dataset import DataError
        from emlpack.data.references import ReferenceError
        from emlpack.train.config import ConfigError, load_config
        from emlpack.train.trainer import train, train_ensemble

        try:
            cfg = load_config(args.config, args.overrides)
            if args.seeds:
                paths = train_ensemble(cfg, args.seeds, resume=not args.restart)
            else:
                paths = [train(cfg, resume=not args.restart)]
        except (ConfigError, DataError, ReferenceError) as exc:
            print(f"emlp train: error: {exc}", file=sys.stderr)
            return 2
        print("best model(s): " + " ".join(str(p) for p in paths))
        return 0

    p.set_defaults(func=run)


def _add_evaluate(sub) -> None:
    p = sub.add_parser("evaluate", help="static/dynamic error tables and parity plots of"
                       " trained model(s) (an ensemble gives mean ± std)")
    p.add_argument("paths", nargs="+", metavar="MODEL... DATA",
                   help="one or more model checkpoints, then the data (extxyz or .h5)")
    p.add_argument("--subset", default="test", choices=["test", "val", "train", "all"],
                   help="subset of the data (the split stored with the model)")
    p.add_argument("-o", "--output", default="evaluation", help="output directory")
    p.add_argument("--no-dynamic", action="store_true", help="skip the pair relaxations")
    p.add_argument("--max-structures", type=int, help="evaluate at most this many")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    def run(args):
        from emlpack.train.evaluate import evaluate_models

        if len(args.paths) < 2:
            print("emlp evaluate: error: give MODEL [MODEL ...] DATA", file=sys.stderr)
            return 2
        try:
            table, _ = evaluate_models(args.paths[:-1], args.paths[-1], args.output,
                                       args.subset, not args.no_dynamic, args.max_structures,
                                       progress=not args.quiet)
        except (ValueError, OSError) as exc:
            print(f"emlp evaluate: error: {exc}", file=sys.stderr)
            return 2
        print(table)
        print(f"wrote {args.output}/evaluation.md, evaluation.json, parity.png")
        return 0

    p.set_defaults(func=run)


def _response_common(p, relax_default: str) -> None:
    p.add_argument("model", help="emlpack model file (.pt)")
    p.add_argument("structure", help="extxyz with Es pairs, or any ASE-readable file (pairs"
                   " are then guessed)")
    p.add_argument("--index", default="0", help="frame in the file (default 0)")
    p.add_argument("--relax", default=relax_default,
                   choices=["none", "pairs", "positions", "cell"],
                   help=f"relax before computing (default {relax_default})")
    p.add_argument("--method", default="newton", choices=["newton", "lbfgs"],
                   help="optimiser for positions/cell")
    p.add_argument("--fmax", type=float, default=1e-6, help="force tolerance (eV/Å)")
    p.add_argument("--guess", default="auto", choices=["auto", "boys", "lewis"],
                   help="pair guess when the file has none")
    p.add_argument("-o", "--output", help="JSON output file")


def _load_for_response(args):
    from emlpack.nn.checkpoint import load_model
    from emlpack.response_tasks import read_input, relax

    model = load_model(args.model)
    s = read_input(args.structure, args.index, args.guess)
    return model, relax(model, s, args.relax, args.method, args.fmax)


def _add_ir(sub) -> None:
    p = sub.add_parser("ir", help="harmonic IR spectrum of a molecule (JSON + PNG)")
    _response_common(p, "positions")
    p.add_argument("--png", help="PNG plot of the spectrum")
    p.add_argument("--fwhm", type=float, default=10.0, help="Lorentzian FWHM (cm^-1)")
    p.add_argument("--reference", help="reference spectrum: text columns cm^-1, km/mol")

    def run(args):
        from emlpack.response_tasks import run_ir

        model, s = _load_for_response(args)
        run_ir(model, s, args.output, args.png, args.fwhm, args.reference)

    p.set_defaults(func=run)


def _add_polarizability(sub) -> None:
    p = sub.add_parser("polarizability", help="dipole and polarizabilities of a molecule")
    _response_common(p, "pairs")

    def run(args):
        from emlpack.response_tasks import run_polarizability

        model, s = _load_for_response(args)
        run_polarizability(model, s, args.output)

    p.set_defaults(func=run)


def _add_response(sub) -> None:
    p = sub.add_parser("response", help="stiffness, dielectric and piezoelectric tensors of"
                       " a crystal")
    _response_common(p, "positions")

    def run(args):
        from emlpack.response_tasks import run_response

        model, s = _load_for_response(args)
        run_response(model, s, args.output)

    p.set_defaults(func=run)


def _add_optimize(sub) -> None:
    p = sub.add_parser("optimize", help="optimise pairs, positions (and the cell) of a"
                       " structure; writes extxyz")
    _response_common(p, "positions")

    def run(args):
        from emlpack.io import write_structures

        _, s = _load_for_response(args)
        out = args.output or "optimized.xyz"
        write_structures(out, [s])
        print(f"wrote {out}")

    p.set_defaults(func=run)


def _add_md(sub) -> None:
    p = sub.add_parser("md", help="Born-Oppenheimer MD with relaxed electron pairs (NVT/NVE,"
                       " optional field); resumable")
    p.add_argument("model", help="emlpack checkpoint (.pt)")
    p.add_argument("start", help="extxyz start structure (pairs as Es rows optional)")
    p.add_argument("--frame", type=int, default=0, help="frame of the start file (0)")
    p.add_argument("--steps", type=int, default=1000, help="total MD steps (1000)")
    p.add_argument("--dt", type=float, default=0.5, help="time step, fs (0.5)")
    p.add_argument("--temperature", type=float, default=300.0,
                   help="K: NVT target and initial velocities (300)")
    p.add_argument("--nve", action="store_true", help="NVE (velocity Verlet) instead of NVT")
    fld = p.add_mutually_exclusive_group()
    fld.add_argument("--field", type=float, nargs=3, metavar=("EX", "EY", "EZ"),
                     help="homogeneous field, V/Å (default: the start file's)")
    fld.add_argument("--field-au", type=float, nargs=3, metavar=("EX", "EY", "EZ"),
                     help="homogeneous field, atomic units")
    p.add_argument("--relax", default="warm", choices=["warm", "corrected", "paper"],
                   help="pair relaxation: warm-started quasi-Newton, the same with a final"
                   " Newton correction (corrected) or the paper's boxed L-BFGS-B")
    p.add_argument("--fmax", type=float, default=1e-5, help="pair-force tolerance, eV/Å")
    p.add_argument("--tdamp", type=float, default=100.0, help="thermostat time constant, fs")
    p.add_argument("--record-every", type=int, default=1, help="frame every N steps (1)")
    p.add_argument("--checkpoint-every", type=int, default=10, help="flush every N steps")
    p.add_argument("--curvature-every", type=int, default=50,
                   help="exact pair Hessian (curvature check) every N steps (50)")
    p.add_argument("--output", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial velocities")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1)")
    p.add_argument("--no-resume", action="store_true", help="start over (deletes the old run)")

    def run(args):
        from emlpack.md import MDWatchdogError, run_md_file

        try:
            result = run_md_file(args)
        except MDWatchdogError as exc:
            print(f"emlp md: watchdog: {exc}", file=sys.stderr)
            return 3
        except ValueError as exc:
            print(f"emlp md: error: {exc}", file=sys.stderr)
            return 2
        print(f"{result.steps} steps, {result.watchdog_events} watchdog events,"
              f" {result.evaluations_per_step:.2f} evaluations/step -> {result.output}")

    p.set_defaults(func=run)


def _add_md_analysis(sub) -> None:
    p = sub.add_parser("md-analysis", help="conserved-quantity stability of MD trajectories"
                       " (slope, max jump per atom; paper's scatter plot)")
    p.add_argument("trajectories", nargs="+", help="extxyz trajectories written by 'emlp md'")
    p.add_argument("--plot", help="scatter plot PNG (|slope| vs max jump, log-log)")
    p.add_argument("--json", help="JSON output with one entry per run")
    p.add_argument("--discard", type=int, default=10, help="initial steps discarded (10)")
    p.add_argument("--groups", nargs="+", help="one group name per trajectory (plot colours)")
    p.add_argument("--series", help="PNG of E_cons(t) per atom of every run")

    def run(args):
        from emlpack.md_analysis import run_analysis

        run_analysis(args.trajectories, args.plot, args.json, args.discard, args.groups,
                     args.series)

    p.set_defaults(func=run)


def _add_md_ir(sub) -> None:
    p = sub.add_parser("md-ir", help="IR spectrum from the dipole autocorrelation of an MD"
                       " trajectory (JSON + PNG)")
    p.add_argument("trajectory", help="extxyz trajectory written by 'emlp md'")
    p.add_argument("-o", "--output", default="md_ir.json", help="JSON output")
    p.add_argument("--png", help="PNG plot")
    p.add_argument("--harmonic", help="'emlp ir' JSON to overlay (harmonic spectrum)")
    p.add_argument("--temperature", type=float, help="K (default: mean of the frames)")
    p.add_argument("--discard", type=int, default=0, help="initial steps discarded")
    p.add_argument("--window", default="hann", choices=["hann", "gaussian", "none"])
    p.add_argument("--correction", default="harmonic",
                   choices=["harmonic", "schofield", "standard", "none"],
                   help="quantum correction factor (default harmonic)")
    p.add_argument("--padding", type=int, default=8, help="zero-padding factor")

    def run(args):
        from emlpack.md_analysis import run_md_ir

        run_md_ir(args.trajectory, args.output, args.png, args.harmonic, args.temperature,
                  args.discard, window=args.window, correction=args.correction,
                  padding=args.padding)

    p.set_defaults(func=run)


def _add_campaign(sub) -> None:
    p = sub.add_parser("campaign", help="a labeling campaign into immutable shards"
                       " (init: molecule list and split; run: label, resumable; card)")
    csub = p.add_subparsers(dest="action", required=True)
    pi = csub.add_parser("init", help="fix the molecule list, its seed and the split")
    pi.add_argument("folder", help="data-set folder, e.g. datasets/mini-eqm7")
    pi.add_argument("--smiles", required=True, help="QM7 SMILES CSV (column 'smiles')")
    pi.add_argument("--seed", type=int, default=0, help="sample and split seed (default 0)")
    pi.add_argument("--n-large", type=int, default=100,
                    help="molecules with 6-7 heavy atoms to draw (default 100)")
    pi.add_argument("--samples-per-molecule", type=int, default=6, help="default 6")
    pr = csub.add_parser("run", help="label the next configurations (resumes from the shards)")
    pr.add_argument("folder")
    pr.add_argument("--workers", type=int, default=2,
                    help="labeling processes (default 2: measured faster than 1 x 2 threads)")
    pr.add_argument("--threads", type=int, help="threads per process (default CPUs/workers)")
    pr.add_argument("--hours", type=float, help="stop after this wall time")
    pr.add_argument("--shard-minutes", type=float, default=20.0,
                    help="finished labels become a new shard this often (default 20)")
    pr.add_argument("--commit", action="store_true", help="git-commit each new shard")
    pr.add_argument("--quiet", action="store_true", help="no progress bar")
    pc = csub.add_parser("card", help="regenerate README.md from the shards")
    pc.add_argument("folder")

    def run(args):
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
                                              samples_per_molecule=args.samples_per_molecule)
                print(f"{args.folder}: {len(mols)} molecules listed")
            elif args.action == "run":
                out = campaign.run_campaign(args.folder, workers=args.workers,
                                            threads=args.threads, hours=args.hours,
                                            shard_minutes=args.shard_minutes,
                                            commit=args.commit, progress=not args.quiet)
                print(f"{args.folder}: {out['new_records']} new configurations,"
                      f" {out['new_failures']} new failures, {len(out['shards'])} shards"
                      f" in {out['wall_s'] / 3600:.2f} h")
            else:
                print(campaign.write_card(args.folder))
        except (SamplingError, StoreError, OSError) as exc:
            print(f"emlp campaign: error: {exc}", file=sys.stderr)
            return 2
        return 0

    p.set_defaults(func=run)


COMMANDS = [_add_train, _add_evaluate, _add_demo, _add_relabel, _add_convert_reference, _add_label]
COMMANDS += [_add_campaign]
COMMANDS += [_add_ir, _add_polarizability, _add_response, _add_optimize]
COMMANDS += [_add_md, _add_md_analysis, _add_md_ir]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="emlp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
