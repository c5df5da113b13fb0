"""``emlp train``, ``evaluate``, ``demo``, ``pretrained``: training, testing and shipped
models."""

from __future__ import annotations

import logging
import sys
from typing import TYPE_CHECKING, TextIO

from emlpack.cli.common import Subparsers, add_parser, load_model, model_files, positive
from emlpack.errors import InputError

if TYPE_CHECKING:
    import argparse


class _StdoutHandler(logging.StreamHandler):
    """Writes to the current ``sys.stdout`` (looked up at each message, so a replaced stream,
    e.g. under pytest, is followed)."""

    @property
    def stream(self):
        return sys.stdout

    @stream.setter
    def stream(self, value: TextIO) -> None:
        pass


def log_to_stdout() -> None:
    """Show the library's INFO messages (a run's settings and progress lines) on stdout, as
    plain lines: the command line's handler (the library installs none). Idempotent."""
    logger = logging.getLogger("emlpack")
    if not any(isinstance(h, _StdoutHandler) for h in logger.handlers):
        handler = _StdoutHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)


def add_train(sub: Subparsers) -> None:
    """Register ``emlp train``: train an eMLP (YAML config + key=value overrides; data parallel
    under torchrun)."""
    p = add_parser(sub, "train", help="train an eMLP (YAML config + key=value overrides;"
                       " data parallel under torchrun)")
    p.add_argument("config", help="YAML config, e.g. configs/small_cpu.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. training.max_epochs=5")
    p.add_argument("--seeds", type=int, nargs="+", help="train an ensemble, one model per seed")
    p.add_argument("--restart", action="store_true",
                   help="start afresh instead of resuming from <output.dir>/last.pt")
    p.add_argument("--device", help="auto, cpu, cuda or cuda:N (default: the config's"
                   " training.device, auto: a CUDA GPU when PyTorch sees one)")

    def run(args: argparse.Namespace):
        from emlpack.data.dataset import DataError
        from emlpack.data.references import HydrideReferenceError
        from emlpack.train.config import ConfigError, load_config
        from emlpack.train.trainer import train, train_ensemble

        log_to_stdout()
        overrides = list(args.overrides)
        if args.threads is not None:  # --threads wins over the config's training.threads
            overrides.append(f"training.threads={args.threads}")
        if args.device is not None:  # so does --device over training.device
            overrides.append(f"training.device={args.device}")
        try:
            cfg = load_config(args.config, overrides)
            if args.seeds:
                paths = train_ensemble(cfg, args.seeds, resume=not args.restart)
            else:
                paths = [train(cfg, resume=not args.restart)]
        except (ConfigError, DataError, HydrideReferenceError) as exc:
            raise InputError(str(exc)) from exc
        print("best model(s): " + " ".join(str(p) for p in paths))
        return 0

    p.set_defaults(func=run, resumable=True)


def add_evaluate(sub: Subparsers) -> None:
    """Register ``emlp evaluate``: static/dynamic error tables and parity plots of trained
    model(s) (an ensemble gives mean ± std)."""
    p = add_parser(sub, "evaluate", help="static/dynamic error tables and parity plots of"
                       " trained model(s) (an ensemble gives mean ± std)")
    p.add_argument("paths", nargs="+", metavar="MODEL... DATA",
                   help="one or more models (checkpoints, ensemble folders or pretrained names"
                   " such as mini-eqm7), then the data (extxyz, .h5 or a shard folder)")
    p.add_argument("--subset", default="test", choices=["test", "val", "train", "all"],
                   help="subset of the data (the split stored with the model)")
    p.add_argument("-o", "--output", default="evaluation", help="output directory")
    p.add_argument("--no-dynamic", action="store_true", help="skip the pair relaxations")
    p.add_argument("--max-structures", type=int, help="evaluate at most this many")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace):
        from emlpack.train.evaluate import evaluate_models

        log_to_stdout()
        if len(args.paths) < 2:
            raise InputError("give MODEL [MODEL ...] DATA")
        # an ensemble folder or a pretrained name stands for its members' files
        files = [f for path in args.paths[:-1] for f in model_files(path)[0]]
        for path in files:
            load_model(str(path))  # the file checks, before the data are read
        positive(args.max_structures, "--max-structures")
        try:
            table, _ = evaluate_models(files, args.paths[-1], args.output,
                                       args.subset, not args.no_dynamic, args.max_structures,
                                       progress=not args.quiet)
        except (ValueError, OSError) as exc:
            raise InputError(str(exc)) from exc
        print(table)
        print(f"wrote {args.output}/evaluation.md, evaluation.json, parity.png")
        return 0

    p.set_defaults(func=run)


def add_demo(sub: Subparsers) -> None:
    """Register ``emlp demo``: run the end-to-end demo on the embedded example data."""
    p = add_parser(sub, "demo", help="run the end-to-end demo on the embedded example data")
    p.add_argument("-o", "--output", default="demo_output", help="output folder")

    def run(args: argparse.Namespace):
        from emlpack.cli.demo import run_demo

        log_to_stdout()
        return run_demo(args.output)

    p.set_defaults(func=run, resumable=True)


def add_pretrained(sub: Subparsers) -> None:
    """Register ``emlp pretrained [NAME]``: list the pretrained models, or show one's card."""
    p = add_parser(sub, "pretrained", help="list the pretrained models, or show one's model"
                   " card, members and spread-warning thresholds")
    p.add_argument("name", nargs="?", metavar="NAME", help="a pretrained name (omit: list)")

    def run(args: argparse.Namespace):
        from emlpack.pretrained import KNOWN, PretrainedError, alias_of, available, model_card

        if args.name is None:
            installed = available()
            for name in sorted(set(KNOWN) | set(installed)):
                status = "installed" if name in installed else "not installed"
                if name in installed and alias_of(name):
                    status += f", the same files as {alias_of(name)}"
                print(f"{name} ({status}): {KNOWN.get(name, 'installed here')}")
            return 0
        if args.name not in available():
            raise PretrainedError(
                f"{args.name}: not an installed pretrained name (installed:"
                f" {', '.join(available()) or 'none'}; 'emlp pretrained' lists them)")
        from emlpack.calculators.ensemble import load_pretrained

        card = model_card(args.name)
        print(card)
        ensemble = load_pretrained(args.name)
        from emlpack.nn.checkpoint import read_checkpoint
        from emlpack.pretrained import LINEAGE_HEADING, lineage_lines

        lineages = []
        for m in ensemble.members:
            print(f"member: {m.source}")
            lineage = (read_checkpoint(m.source).get("metadata") or {}).get("lineage")
            if lineage not in lineages:
                lineages.append(lineage)
        if LINEAGE_HEADING not in card:  # the card shows it already when exported with it
            for lineage in lineages:  # the members' lineages, each once
                for line in lineage_lines(lineage):
                    print(line)
        t = ensemble.spread_thresholds
        print(f"spread warnings above {t.energy:.4g} eV/atom (energy), {t.forces:.4g} eV/Å"
              f" (largest force component): {t.basis}")
        for notice in ensemble.notices:
            print(f"notice: {notice}")
        return 0

    p.set_defaults(func=run)


COMMANDS = [add_train, add_evaluate, add_demo, add_pretrained]
